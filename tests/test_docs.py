"""The front page, the benchmarks' register and the citation file stay true to the repository.

The docs site itself is built with `mkdocs build --strict` by `make test` (broken links, missing
pages and anchors fail there); these checks cover what that build does not see.
"""

from __future__ import annotations

import ast
import re
from pathlib import Path

import yaml

ROOT = Path(__file__).resolve().parents[1]
BENCHMARKS = ROOT / "benchmarks"
HELPERS = {"plan_requests.py"}  # modules the benchmarks import, not benchmarks themselves


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
