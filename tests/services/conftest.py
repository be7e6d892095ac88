import pytest

from services.cli import main
from services.sim.datagen import GenerateConfig, generate


@pytest.fixture(scope="session")
def tiny_model(tmp_path_factory):
    """A tiny dataset (32 px) and a model folder trained on it in seconds: vae/, roadmap/, apn/."""
    root = tmp_path_factory.mktemp("tiny")
    data = root / "train"
    generate(GenerateConfig(pairs=60, seed=1, image_size=32, workers=1), data, progress=False)
    model = root / "model"
    assert (
        main(
            [
                "train",
                "vae",
                "--data",
                str(data),
                "--out",
                str(model / "vae"),
                "--epochs",
                "1",
                "--batch-size",
                "30",
            ]
        )
        == 0
    )
    assert (
        main(
            [
                "build-roadmap",
                "--vae",
                str(model / "vae"),
                "--data",
                str(data),
                "--out",
                str(model / "roadmap"),
                "--min-samples",
                "1",
            ]
        )
        == 0
    )
    assert (
        main(
            [
                "train",
                "apn",
                "--vae",
                str(model / "vae"),
                "--data",
                str(data),
                "--out",
                str(model / "apn"),
                "--epochs",
                "3",
            ]
        )
        == 0
    )
    return model, data
