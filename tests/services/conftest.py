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


@pytest.fixture(scope="session")
def tiny_cloth_model(tmp_path_factory):
    """A tiny cloth dataset (7 x 7 cloth, 32 px) and a model trained on it in seconds."""
    root = tmp_path_factory.mktemp("tiny_cloth")
    data = root / "train"
    cfg = GenerateConfig(
        task="cloth_folding",
        pairs=40,
        seed=3,
        image_size=32,
        workers=1,
        world_options={"lattice": 7},
    )
    generate(cfg, data, progress=False)
    model = root / "model"
    vae, roadmap, apn = (str(model / part) for part in ("vae", "roadmap", "apn"))
    steps = [
        ["train", "vae", "--data", str(data), "--out", vae, "--epochs", "4", "--batch-size", "8"],
        [
            "build-roadmap",
            "--vae",
            vae,
            "--data",
            str(data),
            "--out",
            roadmap,
            "--min-samples",
            "1",
        ],
        ["train", "apn", "--vae", vae, "--data", str(data), "--out", apn, "--epochs", "3"],
    ]
    for args in steps:
        assert main(args) == 0
    return model, data


@pytest.fixture(scope="session")
def patient() -> dict[str, str]:
    """A stack's environment with deadlines long enough for a machine busy with other work:
    for tests that check what a stack does, not how fast (the deadlines' own tests set theirs)."""
    return {"LSR_DEADLINE_S": "60", "LSR_EXECUTE_STEP_S": "30"}
