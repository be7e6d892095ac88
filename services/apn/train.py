"""Training and evaluation of the APN on the latent action pairs of a dataset (paper V)."""

from __future__ import annotations

import json
import math
import time
from collections.abc import Sequence
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
from safetensors.torch import load_file, save_file
from tqdm import tqdm

from services.apn.model import APN, HYBRID_MAX_CLASSES, APNConfig, Head
from services.encoder.checkpoint import encode_images, load_vae
from services.planner.evaluate import TransitionChecker
from shared.checkpoint import read_config, replace_atomically, seal, weights_file
from shared.dataset import load_dataset
from shared.tasks import get_task
from shared.tasks.base import TaskError
from shared.tasks.spec import TaskSpec
from shared.training import minibatches, resolve_device

FORMAT = "lsr-apn"
VERSION = 1


# About the steps the paper's 200 epochs gave the shipped cloth-folding APN (6600: 2080 samples,
# batch 64); with epochs, the 500-tuple run got 1800 and learned a rare move wrong (issue 14).
DEFAULT_STEPS = 8000


@dataclass(frozen=True)
class APNTrainConfig:
    head: Head | None = None  # None: classify small ranges (cells), hybrid when pixels are in it
    steps: int = DEFAULT_STEPS
    epochs: int | None = None  # passes over the training samples instead of `steps`
    batch_size: int = 64
    lr: float = 1e-2
    lr_drops: tuple[float, ...] = (0.25, 0.75)  # lr / 10 after these fractions of the run
    samples: int = 1  # S: draws from q(z|I) added beside the means
    val_fraction: float = 0.2
    # Where the spec declares how a move is undone, each pair also teaches its reverse (the
    # second image to the first, the undoing action): 1000 box tuples demonstrate about a third
    # of the roadmap's edge directions only one way.
    undo: bool = True
    seed: int = 0
    # Runs from fresh weights (seeds seed, seed + 1, ...) on the one split; the lowest
    # validation loss is kept. One T-shirt run in five learned moves wrong (76% named, against
    # 99-100%), and its validation loss said so (4.4e-4 against 5-7e-5).
    restarts: int = 1
    device: str = "auto"  # auto: a CUDA device when present, else the CPU

    def __post_init__(self) -> None:
        if not 0 < self.val_fraction < 1:
            raise ValueError(f"val_fraction must be in (0, 1), got {self.val_fraction}")
        if self.steps < 1 or (self.epochs is not None and self.epochs < 1):
            raise ValueError("steps and epochs must be >= 1")
        if self.restarts < 1:
            raise ValueError(f"restarts must be >= 1, got {self.restarts}")
        if self.samples < 0:
            raise ValueError(f"samples must be >= 0, got {self.samples}")
        if not all(0 <= d <= 1 for d in self.lr_drops):
            raise ValueError(f"lr_drops are fractions of the run, got {self.lr_drops}")

    def total_steps(self, samples: int) -> int:
        """Steps of the run on `samples` training samples (pairs times S + 1)."""
        if self.epochs is None:
            return self.steps
        return self.epochs * math.ceil(samples / self.batch_size)


def action_pair_latents(vae_dir: Path | str, data_dirs: Sequence[Path | str]):
    """Encoder means and log-variances of the action pairs of every dataset (the training
    data, and experience folders of the same task), their action arrays and the first
    dataset's spec (which declares the action's fields and ranges)."""
    model, _ = load_vae(vae_dir)
    parts = []
    spec = None
    for data_dir in data_dirs:
        data = load_dataset(data_dir)
        spec = spec or data.spec
        if data.spec.action != spec.action:
            raise ValueError(f"{data_dir}: its actions differ from {data_dirs[0]}'s")
        if data.image_size != model.config.image_size:
            raise ValueError(
                f"{data_dir}: {data.image_size} px images, the VAE takes {model.config.image_size}"
            )
        act = data.a == 1
        if not act.any():  # experience where every action was refused
            continue
        mu1, lv1 = encode_images(model, data.image1[act])
        mu2, lv2 = encode_images(model, data.image2[act])
        parts.append((mu1, lv1, mu2, lv2, data.u[act].astype(np.int64)))
    if not parts:
        raise ValueError(f"no action pairs in {[str(d) for d in data_dirs]}")
    return spec, *(np.concatenate(column) for column in zip(*parts, strict=True))


def _enlarge(mu1, lv1, mu2, lv2, u, samples: int, rng: np.random.Generator):
    """The means plus `samples` reparameterised draws of every pair (paper: S = 1)."""
    z1, z2 = [mu1], [mu2]
    for _ in range(samples):
        z1.append(mu1 + rng.standard_normal(mu1.shape).astype(np.float32) * np.exp(0.5 * lv1))
        z2.append(mu2 + rng.standard_normal(mu2.shape).astype(np.float32) * np.exp(0.5 * lv2))
    reps = samples + 1
    return (
        torch.from_numpy(np.concatenate(z1)),
        torch.from_numpy(np.concatenate(z2)),
        torch.from_numpy(np.tile(u, (reps, 1))),
    )


def roadmap_node_pairs(roadmap_dir: Path | str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """For every action pair the roadmap holds whose images lie in two nodes: the two nodes'
    latents and the pair's action. A plan asks the APN about exactly these latents."""
    from services.planner.members import Members
    from services.planner.roadmap import Roadmap

    roadmap = Roadmap.load(roadmap_dir)
    members = Members.load(Path(roadmap_dir))
    if len(members.points) != len(roadmap.point_node):
        raise ValueError(f"{roadmap_dir}: its members and roadmap disagree; rebuild it")
    act = np.flatnonzero(members.a == 1)
    first, second = roadmap.point_node[2 * act], roadmap.point_node[2 * act + 1]
    kept = (first >= 0) & (second >= 0) & (first != second)
    nodes = roadmap.nodes.astype(np.float32)
    u = members.actions[act[kept]].reshape(int(kept.sum()), -1).astype(np.int64)
    return nodes[first[kept]], nodes[second[kept]], u


def train_apn(
    vae_dir: Path | str,
    data_dir: Path | str | Sequence[Path | str],
    out_dir: Path | str,
    cfg: APNTrainConfig,
    progress: bool = True,
    roadmap_dir: Path | str | None = None,
) -> dict[str, Any]:
    """The APN on the action pairs of the data; with `roadmap_dir` (a roadmap built on the same
    VAE) its training split also holds every demonstrated edge as the nodes' latents: a plan
    asks about those, and a few hundred tuples teach the T-shirt's moves from them far better
    (same move on unseen pairs 69 -> 89%, issue 47). Validation stays on images alone."""
    torch.manual_seed(cfg.seed)  # before the VAE is built: the first run draws as it always did
    rng = np.random.default_rng(cfg.seed)
    data_dirs = [data_dir] if isinstance(data_dir, str | Path) else list(data_dir)
    spec, mu1, lv1, mu2, lv2, u = action_pair_latents(vae_dir, data_dirs)
    order = rng.permutation(len(u))
    n_val = max(1, round(cfg.val_fraction * len(u)))
    val, train = order[:n_val], order[n_val:]  # split pairs first: no pair on both sides
    undo = cfg.undo and bool(spec.undo)

    def both_ways(*pair: np.ndarray) -> list[tuple[np.ndarray, ...]]:
        z1, v1, z2, v2, action = pair
        return [pair] + ([(z2, v2, z1, v1, spec.undone(action))] if undo else [])

    Parts = Sequence[tuple[np.ndarray, ...]]

    def side(i: np.ndarray, extra: Parts = ()) -> tuple[torch.Tensor, ...]:
        parts = both_ways(mu1[i], lv1[i], mu2[i], lv2[i], u[i]) + list(extra)
        joined = [np.concatenate(column) for column in zip(*parts, strict=True)]
        return _enlarge(*joined, cfg.samples, rng)

    nodes: list[tuple[np.ndarray, ...]] = []
    if roadmap_dir is not None:
        n1, n2, nu = roadmap_node_pairs(roadmap_dir)
        if n1.shape[1] != mu1.shape[1]:
            raise ValueError(f"{roadmap_dir}: {n1.shape[1]}-d nodes, the VAE's latents are "
                             f"{mu1.shape[1]}-d: a roadmap of another VAE")  # fmt: skip
        exact = np.full_like(n1, -80.0)  # log-variance: the draws are the nodes themselves
        nodes = both_ways(n1, exact, n2, exact, nu.reshape(len(nu), *u.shape[1:]))
    tr, va = side(train, nodes), side(val)

    sizes = spec.action.counts
    head = cfg.head or ("classify" if max(sizes) <= HYBRID_MAX_CLASSES else "hybrid")
    device = resolve_device(cfg.device)
    tr, va = tuple(t.to(device) for t in tr), tuple(t.to(device) for t in va)
    config = APNConfig(latent_dim=mu1.shape[1], action_sizes=sizes, head=head)
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    started = time.perf_counter()
    runs = [_fit(config, tr, va, cfg, cfg.seed + r, device, progress) for r in range(cfg.restarts)]
    kept = min(range(cfg.restarts), key=lambda r: runs[r][0]["val_loss"])
    best, best_state, log = runs[kept]
    (out_dir / "log.jsonl").write_text("".join(json.dumps(r) + "\n" for r in log))
    meta = {
        "format": FORMAT,
        "version": VERSION,
        "model": config.to_dict(),
        "train": asdict(cfg)
        | {"head": head, "total_steps": cfg.total_steps(len(tr[2])), "ran_on": str(device)}
        | {"undo": undo},
        "vae": str(vae_dir),
        "dataset": str(data_dirs[0]),
        "experience": [str(d) for d in data_dirs[1:]],
        "task": spec.task,
        "pairs": {"train": len(train), "val": len(val), "train_samples": len(tr[2])},
        "roadmap": None if roadmap_dir is None else str(roadmap_dir),
        "node_pairs": len(nodes[0][0]) if nodes else 0,
        # The training split's action statistics after scaling to [0, 1]: Table II standardises
        # test errors with them, as the paper does.
        "action_scaled": {
            "mean": (u[train] / np.maximum(np.array(sizes) - 1, 1)).mean(0).tolist(),
            "std": (u[train] / np.maximum(np.array(sizes) - 1, 1)).std(0).tolist(),
        },
        "best": best,
        "seconds": time.perf_counter() - started,
    }
    if cfg.restarts > 1:
        meta["restarts"] = {
            "kept_seed": cfg.seed + kept,
            "val_loss": [run[0]["val_loss"] for run in runs],
        }
    text = json.dumps(meta, indent=2) + "\n"
    replace_atomically(out_dir / "apn.safetensors", lambda tmp: save_file(best_state, tmp))
    replace_atomically(out_dir / "config.json", lambda tmp: tmp.write_text(text))
    seal(out_dir, ["apn.safetensors", "config.json"])
    return meta


def _fit(
    config: APNConfig,
    tr: tuple[torch.Tensor, ...],
    va: tuple[torch.Tensor, ...],
    cfg: APNTrainConfig,
    seed: int,
    device: torch.device,
    progress: bool,
) -> tuple[dict[str, Any], dict[str, torch.Tensor], list[dict[str, Any]]]:
    """One run from weights drawn with `seed` (the first run: as the torch generator stands):
    its best validation record, those weights and the validation log."""
    if seed != cfg.seed:
        torch.manual_seed(seed)
    model = APN(config).to(device)
    optimiser = torch.optim.Adam(model.parameters(), lr=cfg.lr)
    total = cfg.total_steps(len(tr[2]))
    per_pass = math.ceil(len(tr[2]) / cfg.batch_size)  # validated after every pass; best kept
    drops = [round(d * total) for d in cfg.lr_drops]
    batches = minibatches(len(tr[2]), cfg.batch_size, torch.Generator().manual_seed(seed))
    best: dict[str, Any] = {"val_loss": float("inf")}
    best_state: dict[str, torch.Tensor] = {}
    log = []
    bar = f"train apn-{config.head}" + (f" (seed {seed})" if seed != cfg.seed else "")
    for step in tqdm(range(total), desc=bar, unit="step", disable=not progress):
        lr = cfg.lr / 10 ** sum(step >= d for d in drops)
        for group in optimiser.param_groups:
            group["lr"] = lr
        model.train()
        idx = next(batches)
        loss = model.loss(model(tr[0][idx], tr[1][idx]), tr[2][idx])
        optimiser.zero_grad(set_to_none=True)
        loss.backward()
        optimiser.step()
        if (step + 1) % per_pass and step + 1 != total:
            continue
        model.eval()
        with torch.no_grad():
            output = model(va[0], va[1])
            val_loss = model.loss(output, va[2]).item()
            both = (model.predict(output)[0] == va[2]).all(-1).float().mean().item()
        record = {
            "step": step + 1,
            "epoch": math.ceil((step + 1) / per_pass),
            "lr": lr,
            "val_loss": val_loss,
            "val_both": 100 * both,
        }
        log.append(record)
        if val_loss < best["val_loss"]:
            best = record
            best_state = {k: v.detach().cpu().clone() for k, v in model.state_dict().items()}
    return best, best_state, log


def load_apn(directory: Path | str) -> tuple[APN, dict[str, Any]]:
    meta = read_config(directory, FORMAT, VERSION, "an APN")
    config = meta["model"] | {"action_sizes": tuple(meta["model"]["action_sizes"])}
    model = APN(APNConfig(**config))
    model.load_state_dict(load_file(weights_file(directory, "apn.safetensors")))
    return model.eval(), meta


@torch.inference_mode()
def propose(model: APN, z1: np.ndarray, z2: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Action arrays and confidences for latent pairs (N, D) -> (N, A), (N,)."""
    action, confidence = model.predict(
        model(torch.from_numpy(z1).float(), torch.from_numpy(z2).float())
    )
    return action.numpy(), confidence.numpy()


def evaluate_apn(apn_dir: Path | str, vae_dir: Path | str, test_dir: Path | str) -> dict:
    """On the unseen action pairs (encoder means): pick, release and both exactly right; for
    pixel actions also the paper's Table II (MSE of the coordinates scaled to [0, 1] and
    standardised), how many pixels the clicks land off, and how often the task's rules see the
    same move as the demonstrator's; where the test data carry states, how often the action,
    applied by the rules from a state looking like the pair's first, gives one looking like its
    second (`leads_to_view`: interface.md, "Views")."""
    model, meta = load_apn(apn_dir)
    spec, mu1, _, mu2, _, u = action_pair_latents(vae_dir, [test_dir])
    predicted, _ = propose(model, mu1, mu2)
    names = spec.action.names
    pick = np.array([n.startswith("pick.") for n in names])
    release = np.array([n.startswith("release.") for n in names])
    exact = predicted == u
    pick_ok, release_ok = exact[:, pick].all(1), exact[:, release].all(1)
    out: dict[str, Any] = {
        "apn": str(apn_dir),
        "head": meta["model"]["head"],
        "test_action_pairs": len(u),
        "pick": 100.0 * pick_ok.mean(),
        "release": 100.0 * release_ok.mean(),
        "both": 100.0 * exact.all(1).mean(),
        "per_field": per_field_errors(spec, predicted, u, meta.get("action_scaled")),
    }
    leads = _leads_to_view(spec, test_dir, predicted)
    if leads is not None:
        out["leads_to_view"] = leads
    if spec.action.pixels:
        scaling = meta.get("action_scaled")
        if scaling is None:
            raise ValueError(f"{apn_dir}: no training statistics (action_scaled); retrain it")
        out |= pixel_action_errors(spec, predicted, u, np.array(scaling["std"]))
    return out


def _leads_to_view(spec: TaskSpec, test_dir: Path | str, predicted: np.ndarray) -> float | None:
    """% of the test action pairs whose predicted action leads, by the task's rules, from the
    first image's view to the second's; None for a task without states or rules."""
    data = load_dataset(test_dir)
    if data.spec.state is None:
        return None
    try:
        task = get_task(spec.task)
    except TaskError:
        return None
    act = data.a == 1
    checker = TransitionChecker(task)
    ok = [
        checker.actions_lead(
            [task.array_to_state(s1), task.array_to_state(s2)], [task.array_to_action(p)]
        )
        for s1, s2, p in zip(data.state1[act], data.state2[act], predicted, strict=True)
    ]
    return 100.0 * float(np.mean(ok))


def per_field_errors(
    spec: TaskSpec, predicted: np.ndarray, true: np.ndarray, scaled: dict | None
) -> dict[str, dict[str, float]]:
    """Each field's exact-match rate and, as Table II does, its squared error on the [0, 1]
    scale standardised with the training split's spread (when the APN recorded it)."""
    counts = np.array(spec.action.counts, dtype=np.float64)
    std = np.ones(len(counts)) if scaled is None else np.array(scaled["std"], dtype=np.float64)
    std = np.where(std > 0, std, 1.0)
    error = ((predicted - true) / np.maximum(counts - 1, 1) / std) ** 2
    return {
        name: {
            "exact": 100.0 * float((predicted[:, i] == true[:, i]).mean()),
            "mse": float(error[:, i].mean()),
            "mean_abs": float(np.abs(predicted[:, i] - true[:, i]).mean()),
        }
        for i, name in enumerate(spec.action.names)
    }


def pixel_action_errors(
    spec: TaskSpec, predicted: np.ndarray, true: np.ndarray, train_std: np.ndarray
) -> dict:
    """Table II of the paper for pixel actions (squared error of the action scaled to [0, 1]
    and standardised with the training split's statistics), errors in pixels and in moves."""
    names = list(spec.action.names)
    counts = np.array(spec.action.counts, dtype=np.float64)
    std = np.where(train_std > 0, train_std, 1.0)
    part = {
        k: [i for i, n in enumerate(names) if n.startswith(k + ".")] for k in ("pick", "release")
    }

    def table2(guess: np.ndarray) -> dict[str, float]:
        # Summed over the elements of each part, as the paper's totals (4.47 = 2.12 pick +
        # 2.21 release + the height's share).
        per_element = (((guess - true) / np.maximum(counts - 1, 1) / std) ** 2).mean(0)
        return {
            "pick": float(per_element[part["pick"]].sum()),
            "release": float(per_element[part["release"]].sum()),
            "total": float(per_element.sum()),
        }

    out: dict[str, Any] = {"mse": table2(predicted)}
    for key, idx in part.items():
        pixel = [i for i in idx if names[i] in spec.action.pixels]
        distance = np.linalg.norm(predicted[:, pixel] - true[:, pixel], axis=1)
        out[f"{key}_pixels"] = {
            "mean": float(distance.mean()),
            "median": float(np.median(distance)),
            "p95": float(np.percentile(distance, 95)),
        }
    others = [i for i, n in enumerate(names) if n not in spec.action.pixels]
    if others:
        exact = (predicted[:, others] == true[:, others]).all(1)
        out["other_fields_exact"] = 100.0 * float(exact.mean())
    try:
        task = get_task(spec.task)
    except TaskError:
        return out
    if hasattr(task, "match"):  # a task that matches clicks to moves: did the APN name the move?
        moves = [task.match(task.array_to_action(t)) for t in true]
        same = [
            task.match(task.array_to_action(p)) == m for p, m in zip(predicted, moves, strict=True)
        ]
        out["same_move"] = 100.0 * float(np.mean(same))
        if all(m is not None for m in moves):  # the error of naming each move's exact point:
            canonical = np.stack([task.action_to_array(m.action) for m in moves])
            out["mse_click_noise"] = table2(canonical)  # what the demonstrators' noise costs
    return out
