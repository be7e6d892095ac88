# One image for every LSR process: the encoder, planner, apn and sim services and the REST
# gateway; docker-compose.yml picks the process with `lsr serve NAME`.
#   docker build -t lsr:local .
# The install steps are the Makefile's (tests/test_deploy.py checks they stay the same): upgrade
# pip, torch==2.13.0 first (CPU build), then the project.
FROM python:3.11-slim-bookworm

# Where torch comes from: PyPI's linux wheel of torch 2.13.0 pulls the CUDA libraries (GBs), this
# index has the CPU build. Used by the torch install only; everything else comes from PyPI.
ARG TORCH_INDEX_URL=https://download.pytorch.org/whl/cpu

ENV PYTHONDONTWRITEBYTECODE=1 \
    PYTHONUNBUFFERED=1 \
    PIP_NO_CACHE_DIR=1 \
    PIP_DISABLE_PIP_VERSION_CHECK=1 \
    MUJOCO_GL=egl \
    VIRTUAL_ENV=/opt/venv \
    PATH=/opt/venv/bin:$PATH

# Offscreen rendering without a GPU or display: MuJoCo -> EGL (surfaceless) -> Mesa's software
# rasteriser (llvmpipe). The packages:
#   libegl1          libEGL.so.1, glvnd's EGL dispatcher that MuJoCo's EGL backend (PyOpenGL) loads
#   libegl-mesa0     Mesa's EGL vendor library, which glvnd dispatches to
#   libgl1-mesa-dri  Mesa's drivers, among them the software one (swrast/llvmpipe)
#   libgl1           libGL.so.1, where PyOpenGL looks up the desktop GL functions MuJoCo calls
# libgles2 is left out: PyOpenGL falls back to GLESv2 only when libGL is missing.
RUN apt-get update \
    && apt-get install -y --no-install-recommends libegl1 libegl-mesa0 libgl1-mesa-dri libgl1 \
    && rm -rf /var/lib/apt/lists/*

RUN python -m venv "$VIRTUAL_ENV"
RUN "$VIRTUAL_ENV"/bin/pip install --upgrade pip
RUN "$VIRTUAL_ENV"/bin/pip install --index-url "$TORCH_INDEX_URL" torch==2.13.0

WORKDIR /app
COPY pyproject.toml README.md ./
COPY services ./services
COPY shared ./shared
RUN "$VIRTUAL_ENV"/bin/pip install .

# A home of its own: Mesa's shader cache and matplotlib's config go under ~/.cache and ~/.config.
RUN useradd --create-home --uid 10001 lsr
USER lsr
WORKDIR /home/lsr

CMD ["lsr", "--help"]
