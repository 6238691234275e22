"""Train the reference in-domain VLA on the seen tasks' keyframes: ``python -m agnostos_mjx.train.vla``.

python -m agnostos_mjx.train.vla_data --out data/vla --tasks seen --demos 100 --workers 16
python -m agnostos_mjx.train.vla --data data/vla --out runs/vla
python -m agnostos_mjx.eval --policy reference-vla --policy-arg checkpoint=runs/vla --tasks seen
python -m agnostos_mjx.train.vla --quick --tasks open_drawer,push_buttons --demos 2 --out /tmp/v

The data are keyframe samples (train/vla_data.py); with ``--quick`` and no ``--data`` they
are generated first (into ``<out>/data``).  Every step renders the batch's virtual views
on the device from the stored point clouds, after a random translation of the whole
scene and its targets (``--augment``, metres), and picks one of the variation's
instructions at random.  Demos i with i % holdout_every == holdout_every - 1 are held
out; every ``--sample-every`` steps their keyframes are predicted and the position error,
rotation-bin and gripper accuracy go to ``heldout.jsonl`` (and stderr).  The loop,
checkpoints and resume are the dynamics training's (train/common.py).
"""

from __future__ import annotations

import json
import sys
from dataclasses import replace
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from flax import nnx

from agnostos_mjx.dynamics.config import TrainConfig, add_flags, apply_flags
from agnostos_mjx.dynamics.text import tokenize
from agnostos_mjx.infra.settings import configure_jax
from agnostos_mjx.sim.textualise import quat_to_euler_bins
from agnostos_mjx.train.common import run_parser, train
from agnostos_mjx.vla.checkpoint import run_meta
from agnostos_mjx.vla.model import (
    VLA_DEFAULT,
    VLA_QUICK,
    ReferenceVLA,
    VLAConfig,
    gripper_bins,
    predict,
    vla_loss,
)
from agnostos_mjx.vla.views import render_views

# ~20 epochs of the 100-demo seen data (12.5 k training keyframes) at batch 32.
TRAIN_DEFAULT = TrainConfig(steps=8_000, batch_size=32, lr=3e-4, warmup=500, log_every=100,
                            sample_every=2_000, ckpt_every=2_000)
TRAIN_QUICK = TrainConfig(steps=30, batch_size=8, lr=2e-3, warmup=0, log_every=5,
                          sample_every=0, ckpt_every=30)
PRECISIONS = ("default", "tensorfloat32", "bfloat16")
_ARRAYS = ("rgb", "points", "gripper_pose", "gripper_open", "step", "demo", "variation",
           "target_pos", "target_quat", "target_gripper")


class KeyframeData:
    """Every chunk of a vla_data directory, concatenated, with the instructions tokenised."""

    def __init__(self, directory: Path, text_len: int, tasks: tuple[str, ...] | None = None):
        files = sorted(Path(directory).glob("*_[0-9][0-9][0-9][0-9][0-9].npz"))
        if not files:
            raise ValueError(f"{directory}: no keyframe chunks (python -m agnostos_mjx.train.vla_data)")
        try:
            manifest = json.loads((Path(directory) / "manifest.json").read_text())["settings"]
        except (OSError, ValueError, KeyError) as err:
            raise ValueError(f"{directory}: no readable manifest.json ({err})") from None
        self.cameras, self.size = tuple(manifest["cameras"]), int(manifest["size"])
        parts: dict[str, list] = {k: [] for k in (*_ARRAYS, "desc_start", "desc_count", "task")}
        texts: list[str] = []
        self.tasks: list[str] = []
        for f in files:
            with np.load(f) as z:
                task = str(z["task"])
                if tasks is not None and task not in tasks:
                    continue
                if task not in self.tasks:
                    self.tasks.append(task)
                descriptions = {int(v): d for v, d in json.loads(str(z["descriptions"])).items()}
                starts = {}
                for v, d in sorted(descriptions.items()):
                    starts[v] = (len(texts), len(d))
                    texts += d
                for k in _ARRAYS:
                    parts[k].append(z[k])
                var = z["variation"]
                parts["desc_start"].append(np.array([starts[int(v)][0] for v in var]))
                parts["desc_count"].append(np.array([starts[int(v)][1] for v in var]))
                parts["task"].append(np.full(len(var), self.tasks.index(task)))
        if not self.tasks:
            raise ValueError(f"{directory}: none of the tasks {tasks} in the data")
        self.arrays = {k: np.concatenate(v) for k, v in parts.items()}
        self.texts = texts
        self.ids, self.mask = tokenize(texts, text_len)
        a = self.arrays
        a["target_rot"] = quat_to_euler_bins(a["target_quat"])
        a["target_grip"] = np.asarray(gripper_bins(a["target_gripper"]))
        a["gripper_pos"] = a["gripper_pose"][:, :3]

    def __len__(self) -> int:
        return len(self.arrays["step"])

    def split(self, holdout_every: int) -> tuple[np.ndarray, np.ndarray]:
        """Indices of training and held-out samples (by demo index, as the dynamics split)."""
        held = self.arrays["demo"] % holdout_every == holdout_every - 1
        return np.nonzero(~held)[0], np.nonzero(held)[0]


_BATCH_KEYS = ("rgb", "points", "gripper_pos", "gripper_open", "step", "target_pos",
               "target_rot", "target_grip", "desc_start", "desc_count")


def batch_inputs(batch: dict[str, jax.Array], key: jax.Array | None, ids: jax.Array,
                 mask: jax.Array, cfg: VLAConfig, augment: float) -> dict[str, jax.Array]:
    """Stored samples -> the model's inputs: a random instruction of the variation and a
    random translation of the scene (when `key` is given), then the virtual views."""
    b = batch["step"].shape[0]
    points = batch["points"].reshape(b, -1, 3).astype(jnp.float32)
    rgb = batch["rgb"].reshape(b, -1, 3)
    grip, target = batch["gripper_pos"], batch["target_pos"]
    pick = batch["desc_start"]
    if key is not None:
        k1, k2 = jax.random.split(key)
        pick = pick + jnp.floor(jax.random.uniform(k1, (b,)) * batch["desc_count"]).astype(
            pick.dtype)
        shift = jax.random.uniform(k2, (b, 3), minval=-augment, maxval=augment)
        points, grip, target = points + shift[:, None], grip + shift, target + shift
    return {"views": render_views(points, rgb, grip, cfg.view_size), "ids": ids[pick],
            "mask": mask[pick], "gripper_open": batch["gripper_open"], "step": batch["step"],
            "target_pos": target, "target_rot": batch["target_rot"],
            "target_grip": batch["target_grip"]}


def heldout_metrics(model: ReferenceVLA, data: KeyframeData, held: np.ndarray,
                    cfg: VLAConfig, batch: int = 64) -> dict[str, float]:
    """Held-out keyframe accuracy: position error (m), share within 1 and 2 cm, all three
    Euler bins right (exact and within one bin), gripper amount right (to 0.1)."""
    ids, mask = jnp.asarray(data.ids), jnp.asarray(data.mask)

    @nnx.jit
    def run(model, b):
        x = batch_inputs(b, None, ids, mask, cfg, 0.0)
        return predict(model, x["views"], x["ids"], x["mask"], x["gripper_open"], x["step"])

    errs, rot_ok, rot_near, grip_ok = [], [], [], []
    a = data.arrays
    for s in range(0, len(held), batch):
        idx = held[s: s + batch]
        pos, bins, grip = map(np.asarray, run(model, {k: a[k][idx] for k in _BATCH_KEYS}))
        errs.append(np.linalg.norm(pos - a["target_pos"][idx], axis=-1))
        d = np.abs(bins - a["target_rot"][idx])
        d = np.minimum(d, 72 - d)
        rot_ok.append((d == 0).all(-1))
        rot_near.append((d <= 1).all(-1))
        grip_ok.append(np.abs(grip - a["target_gripper"][idx]) < 0.05)
    e = np.concatenate(errs)
    return {"samples": int(len(e)), "pos_err_mean": float(e.mean()),
            "pos_err_median": float(np.median(e)), "within_1cm": float((e < 0.01).mean()),
            "within_2cm": float((e < 0.02).mean()),
            "rot_exact": float(np.concatenate(rot_ok).mean()),
            "rot_within_1bin": float(np.concatenate(rot_near).mean()),
            "gripper": float(np.concatenate(grip_ok).mean())}


def train_vla(data: KeyframeData, cfg: VLAConfig, tcfg: TrainConfig, out: Path,
              augment: float = 0.1, progress: bool = True,
              max_seconds: float | None = None) -> ReferenceVLA:
    """Train (or resume) a reference VLA run in `out` (stopping early after `max_seconds`)."""
    train_idx, held_idx = data.split(tcfg.holdout_every)
    if len(train_idx) == 0:
        raise ValueError("no training samples: every demo is held out")
    device = {k: jnp.asarray(data.arrays[k][train_idx]) for k in _BATCH_KEYS}
    ids, mask = jnp.asarray(data.ids), jnp.asarray(data.mask)
    out.mkdir(parents=True, exist_ok=True)

    def get_batch(idx: np.ndarray) -> dict[str, jax.Array]:
        j = jnp.asarray(idx)
        return {k: v[j] for k, v in device.items()}

    def loss_fn(model: ReferenceVLA, batch: Any, key: jax.Array) -> jax.Array:
        return vla_loss(model, batch_inputs(batch, key, ids, mask, cfg, augment))[0]

    def sample(model: ReferenceVLA, step: int) -> None:
        if not len(held_idx):
            return
        rec = {"step": step, **heldout_metrics(model, data, held_idx, cfg)}
        with open(out / "heldout.jsonl", "a") as f:
            f.write(json.dumps(rec) + "\n")
        print("held-out " + " ".join(f"{k} {v:.4g}" if isinstance(v, float) else f"{k} {v}"
                                     for k, v in rec.items()), file=sys.stderr, flush=True)

    meta = {**run_meta(cfg, data.cameras, data.size), "tasks": data.tasks,
            "max_key_actions": int(data.arrays["step"].max()) + 1,
            "augment": augment, "samples": {"train": int(len(train_idx)),
                                            "heldout": int(len(held_idx))}}
    return train(lambda: ReferenceVLA(cfg, rngs=nnx.Rngs(tcfg.seed)), loss_fn, get_batch,
                 len(train_idx), tcfg, out, meta, sample, progress, max_seconds)


def parser():
    p = run_parser("python -m agnostos_mjx.train.vla", __doc__)
    p.add_argument("--data", type=Path, help="keyframe data directory (train/vla_data.py)")
    p.add_argument("--tasks", help="train on these tasks of the data only (names, splits)")
    p.add_argument("--quick", action="store_true",
                   help="tiny model and 30 steps (CPU smoke run); without --data it first "
                   "generates --demos demos of --tasks into <out>/data (32 px, 2 cameras)")
    p.add_argument("--demos", type=int, default=2, help="--quick without --data: demos per task")
    p.add_argument("--augment", type=float, default=0.1,
                   help="random scene translation per sample, +- metres per axis (0: none)")
    p.add_argument("--max-seconds", type=float,
                   help="stop early (checkpoint saved) after this many seconds of training; "
                   "the schedule stays that of --steps, and a rerun resumes")
    p.add_argument("--export", type=Path, metavar="DIR",
                   help="write the float16 export of the run's latest checkpoint to DIR (after "
                   "training; without --data and --quick: only that)")
    p.add_argument("--curve", action="store_true",
                   help="print the run's training curve (held-out accuracy and loss) as "
                   "markdown and exit")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.add_argument("--matmul-precision", choices=PRECISIONS, default="default",
                   help="JAX matmul/conv precision of training (jax.default_matmul_precision): "
                   "tensorfloat32 or bfloat16 trade mantissa bits for tensor-core speed on a "
                   "GPU (tools/vla_step_profile.py measures it); no effect on a CPU")
    add_flags(p, "vla", VLA_DEFAULT, VLA_QUICK)
    add_flags(p, "train", TRAIN_DEFAULT, TRAIN_QUICK)
    return p


def main(argv: list[str] | None = None) -> int:
    configure_jax()
    from agnostos_mjx.tasks import parse_tasks
    from agnostos_mjx.train.vla_data import DataConfig, generate

    p = parser()
    args = p.parse_args(argv)
    try:
        tasks = None if args.tasks is None else tuple(t.name for t in parse_tasks(args.tasks))
        cfg = apply_flags(args, "vla", VLA_QUICK if args.quick else VLA_DEFAULT)
        tcfg = apply_flags(args, "train", TRAIN_QUICK if args.quick else TRAIN_DEFAULT)
    except (KeyError, ValueError) as err:
        p.error(str(err.args[0] if isinstance(err, KeyError) else err))
    data_dir = args.data
    if args.curve:
        print(curve(args.out), end="")
        return 0
    if data_dir is None and args.export is not None and not args.quick:
        return _export(args.out, args.export)
    if data_dir is None:
        if not args.quick:
            p.error("give --data DIR (python -m agnostos_mjx.train.vla_data), or --quick")
        data_dir = args.out / "data"
        quick_tasks = tasks or ("open_drawer", "push_buttons")
        generate(DataConfig(data_dir, quick_tasks, args.demos, ("front", "overhead"), 32,
                            chunk=max(1, args.demos)))
        if args.demos < tcfg.holdout_every:  # a tiny run holds out its last demo per task
            tcfg = replace(tcfg, holdout_every=args.demos)
    if not Path(data_dir).is_dir():
        p.error(f"--data {data_dir}: no such directory")
    try:
        data = KeyframeData(data_dir, cfg.text_len, tasks)
        precision = None if args.matmul_precision == "default" else args.matmul_precision
        with jax.default_matmul_precision(precision):
            train_vla(data, cfg, tcfg, args.out, args.augment, not args.no_progress,
                      args.max_seconds)
    except ValueError as err:
        print(f"train.vla: {err}", file=sys.stderr)
        return 2
    print(f"reference VLA run in {args.out}: {len(data)} keyframes of {len(data.tasks)} tasks; "
          f"evaluate with python -m agnostos_mjx.eval --policy reference-vla "
          f"--policy-arg checkpoint={args.out}")
    return 0 if args.export is None else _export(args.out, args.export)


def curve(run: Path) -> str:
    """The run's training curve as markdown: held-out keyframe accuracy at each sample
    point beside the training loss logged at that step (log.jsonl, heldout.jsonl)."""
    def rows(name: str) -> list[dict]:
        path = run / name
        return [json.loads(x) for x in path.read_text().splitlines() if x] if path.exists() else []

    loss = {r["step"]: r for r in rows("log.jsonl")}
    lines = ["| step | train loss | seconds | held-out pos err mean / median (cm) | within 1 / 2 cm "
             "| rotation exact / within 1 bin | gripper |", "|---|---|---|---|---|---|---|"]
    for h in rows("heldout.jsonl"):
        r = loss.get(h["step"], {})
        lines.append(
            f"| {h['step']} | {r.get('loss', float('nan')):.3f} | {r.get('seconds', '')} | "
            f"{100 * h['pos_err_mean']:.1f} / {100 * h['pos_err_median']:.1f} | "
            f"{h['within_1cm']:.2f} / {h['within_2cm']:.2f} | {h['rot_exact']:.2f} / "
            f"{h['rot_within_1bin']:.2f} | {h['gripper']:.2f} |")
    return "\n".join(lines) + "\n"


def _export(run: Path, out: Path) -> int:
    from agnostos_mjx.dynamics.checkpoint import CheckpointError
    from agnostos_mjx.vla.checkpoint import export

    try:
        info = export(run, out)
    except CheckpointError as err:
        print(f"train.vla: {err}", file=sys.stderr)
        return 2
    size = sum(f.stat().st_size for f in out.iterdir()) / 1e6
    print(f"export of {run} (step {info['source']['step']}, {info['parameters']:,} "
          f"parameters) in {out}: {size:.1f} MB")
    return 0


if __name__ == "__main__":
    sys.exit(main())
