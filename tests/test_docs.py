"""The front page, the docs' pages, the benchmarks' register and the citation file stay true
to the repository.

The docs site itself is built with `mkdocs build --strict` by `make test` (broken links, missing
pages and anchors fail there); these checks cover what that build does not see: the repository
paths the pages name in their text and the model digests they give.
"""

from __future__ import annotations

import ast
import hashlib
import re
import shutil
import subprocess
from functools import cache
from pathlib import Path

import pytest
import yaml

from shared.settings import shipped_models

ROOT = Path(__file__).resolve().parents[1]
BENCHMARKS = ROOT / "benchmarks"
HELPERS = {"plan_requests.py"}  # modules the benchmarks import, not benchmarks themselves
PAGES = [ROOT / "README.md", *sorted((ROOT / "docs").rglob("*.md"))]

# A repository path in a page's text: one of the project's top folders, then the rest. Not
# inside another path or a URL (`runs/x/models/...`, `http://host:8000/docs`).
REPO_PATH = re.compile(
    r"(?<![\w./:~$-])(?:benchmarks|deploy|docs|examples|models|services|shared|tests|\.ci)/"
    r"[\w./*<>{}-]*"
)
# Placeholders, not paths: `<task>`, `{task}`, `...`, an upper-case name (`benchmarks/NAME.py`).
PLACEHOLDER = re.compile(r"[<>{}]|\.\.\.|(?:^|/)[A-Z][A-Z0-9_]*(?:\.py|\.sh)?(?:/|$)")
# A file digest or model id: 8 to 64 hex digits, at least one a letter (so no plain number).
DIGEST = re.compile(r"(?<![0-9A-Za-z_])(?=[0-9]*[a-f])[0-9a-f]{8,64}(?![0-9A-Za-z_])")
COMMIT = re.compile(r"(?<![0-9A-Za-z_])[0-9a-f]{7}(?![0-9A-Za-z_])")  # as the pages cite one
MODEL_FOLDER = re.compile(r"(?<![\w/])models/(\w+)")
CLAIMS_A_MODEL = re.compile(r"\b(?:shipped|built-in)\b|model[ _]id", re.I)


def test_the_readme_is_a_signpost_whose_links_all_exist():
    readme = (ROOT / "README.md").read_text()
    assert len(readme.splitlines()) <= 200
    targets = re.findall(r"\]\(([^)#\s]+)(?:#[^)]*)?\)", readme)
    local = [t for t in targets if "://" not in t]
    assert len(local) > 20  # it points into the docs, not at itself
    for target in local:
        assert (ROOT / target).exists(), f"README.md links {target}, which does not exist"


def test_every_benchmark_is_registered_with_its_command():
    scripts = {p.name for p in BENCHMARKS.iterdir() if p.suffix in {".py", ".sh"}}
    page = (ROOT / "docs" / "benchmarks.md").read_text()
    listed = set(re.findall(r"^\| `([\w.]+\.(?:py|sh))` \|", page, re.M))
    assert listed == scripts, (
        f"docs/benchmarks.md lacks {sorted(scripts - listed)}; lists {sorted(listed - scripts)}"
    )
    for name in sorted(scripts - HELPERS):
        text = (BENCHMARKS / name).read_text()
        if name.endswith(".py"):
            doc = ast.get_docstring(ast.parse(text)) or ""
            assert f"benchmarks/{name}" in doc, f"{name}: its docstring names no command"
            assert '__name__ == "__main__"' in text, f"{name}: runs on import"
        else:
            header = text.split("set -", 1)[0]
            assert "# Usage:" in header, f"{name}: its header says no usage"


def test_the_citation_file_cites_the_project_and_the_paper():
    cff = yaml.safe_load((ROOT / "CITATION.cff").read_text())
    assert cff["cff-version"] == "1.2.0"
    assert {"message", "title", "authors", "version", "license"} <= set(cff)
    pyproject = (ROOT / "pyproject.toml").read_text()
    assert f'version = "{cff["version"]}"' in pyproject
    paper = cff["preferred-citation"]
    assert paper["title"].startswith("Latent Space Roadmap for Visual Action Planning")
    assert paper["authors"][0]["family-names"] == "Lippi" and paper["year"] == 2020


def output_folders() -> tuple[str, ...]:
    """What the commands write (.gitignore's anchored entries: data/, runs/, deploy/zenoh/)."""
    lines = (ROOT / ".gitignore").read_text().splitlines()
    return tuple(line.strip("/") + "/" for line in lines if line.startswith("/"))


def test_every_repository_path_a_page_names_exists():
    """`services/...`, `models/...` and the like in README.md and docs/ name what is there;
    what commands write (data/, runs/) and placeholders are not checked."""
    outputs = output_folders()
    checked, missing = 0, []
    for page in PAGES:
        for number, line in enumerate(page.read_text().splitlines(), 1):
            for found in REPO_PATH.finditer(line):
                path = found.group(0).rstrip(".")
                if PLACEHOLDER.search(found.group(0)) or (path + "/").startswith(outputs):
                    continue
                checked += 1
                exists = any(ROOT.glob(path)) if "*" in path else (ROOT / path).exists()
                if not exists:
                    missing.append(f"{page.relative_to(ROOT)}:{number}: {path}")
    assert checked > 100  # the pattern finds the pages' paths
    assert not missing, "pages name paths the repository does not have:\n" + "\n".join(missing)


def passages(text: str):
    """A page's paragraphs, each table row its own: what one claim can span."""
    block: list[str] = []
    for line in text.splitlines():
        if line.startswith("|") or not line.strip():
            if block:
                yield "\n".join(block)
                block = []
            if line.startswith("|"):
                yield line
        else:
            block.append(line)
    if block:
        yield "\n".join(block)


def file_digests(folder: Path) -> set[str]:
    return {
        hashlib.sha256(path.read_bytes()).hexdigest()
        for path in folder.rglob("*")
        if path.is_file()
    }


def git(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run(["git", "-C", str(ROOT), *args], capture_output=True, timeout=60)


@cache
def has_commit(commit: str) -> bool:
    """Whether git can show `commit` here (not in a shallow clone or an export without .git)."""
    if shutil.which("git") is None:
        return False
    return git("cat-file", "-e", f"{commit}^{{commit}}").returncode == 0


@cache
def digests_at(commit: str, folder: str) -> frozenset[str]:
    """sha256 of every file under `folder` at `commit`."""
    names = git("ls-tree", "-r", "--name-only", commit, "--", folder).stdout.decode().split()
    blobs = (git("cat-file", "blob", f"{commit}:{name}").stdout for name in names)
    return frozenset(hashlib.sha256(blob).hexdigest() for blob in blobs)


def test_every_model_digest_a_page_gives_is_that_models_own():
    """A digest (or model id, its first 12 hex digits) in a paragraph or table row that names a
    shipped model is the sha256 of one of that model's files, or of one at a commit the same
    passage names (an earlier model, as it was then)."""
    shipped = [folder.name for folder in shipped_models()]  # what `lsr up` serves
    now = {folder.name: file_digests(folder) for folder in shipped_models()}
    wrong, unverifiable = [], []
    for page in PAGES:
        for passage in passages(page.read_text()):
            digests = DIGEST.findall(passage)
            if not digests:
                continue
            named = sorted(set(MODEL_FOLDER.findall(passage)) & set(shipped))
            if not named and not CLAIMS_A_MODEL.search(passage):
                continue  # no model is named: not a claim about one
            folders = named or shipped
            commits = COMMIT.findall(passage)
            for digest in digests:
                if any(d.startswith(digest) for name in folders for d in now[name]):
                    continue
                where = f"{page.relative_to(ROOT)}: {digest} ({', '.join(folders)})"
                if commits and not all(map(has_commit, commits)):
                    unverifiable.append(where)
                    continue
                then = (digests_at(c, f"models/{name}") for c in commits for name in folders)
                if not any(d.startswith(digest) for found in then for d in found):
                    wrong.append(where)
    assert not wrong, (
        "digests given as a shipped model's that are not its files' (nor at a commit the "
        "passage names):\n" + "\n".join(wrong)
    )
    if unverifiable:
        pytest.skip("git cannot show the commits these name: " + "; ".join(unverifiable))
