"""The training loop both stages share: AdamW with warm-up + cosine decay, a
jitted step, deterministic per-step batches (so a resumed run sees the batches
an uninterrupted one would), JSONL loss log, progress bar, periodic checkpoints
and sample grids."""

from __future__ import annotations

import argparse
import json
import struct
import sys
import time
import zlib
from collections.abc import Callable
from pathlib import Path
from typing import Any

import jax
import numpy as np
import optax
from flax import nnx

from agnostos_mjx.dynamics.checkpoint import Checkpoints
from agnostos_mjx.dynamics.config import PRESETS, Preset, TrainConfig, to_dict
from agnostos_mjx.dynamics.data import FramePairs, synthetic
from agnostos_mjx.dynamics.layers import abstract, create

LossFn = Callable[[nnx.Module, Any, jax.Array], jax.Array]  # (model, batch, key) -> scalar


def optimizer(cfg: TrainConfig) -> optax.GradientTransformation:
    """Clipped AdamW; learning rate: linear warm-up from 0 (none if warmup = 0), then cosine to 5%."""
    steps = max(cfg.steps, cfg.warmup + 1)
    if cfg.warmup > 0:
        lr = optax.warmup_cosine_decay_schedule(0.0, cfg.lr, cfg.warmup, steps, cfg.lr * 0.05)
    else:
        lr = optax.cosine_decay_schedule(cfg.lr, steps, alpha=0.05)
    return optax.chain(
        optax.clip_by_global_norm(cfg.grad_clip), optax.adamw(lr, weight_decay=cfg.weight_decay)
    )


def batch_indices(cfg: TrainConfig, n: int, step: int) -> np.ndarray:
    """The batch of `step`: a function of (seed, step) only."""
    rng = np.random.default_rng([cfg.seed, step])
    return rng.choice(n, cfg.batch_size, replace=n < cfg.batch_size)


def make_step(
    graphdef: nnx.GraphDef, tx: optax.GradientTransformation, loss_fn: LossFn
) -> Callable:
    """The jitted update: (params, opt_state, batch, key) -> (params, opt_state, loss)."""

    @jax.jit
    def step(params: nnx.State, opt_state: Any, batch: Any, key: jax.Array):
        loss, grads = jax.value_and_grad(lambda p: loss_fn(nnx.merge(graphdef, p), batch, key))(
            params
        )
        updates, opt_state = tx.update(grads, opt_state, params)
        return optax.apply_updates(params, updates), opt_state, loss

    return step


def train(
    build: Callable[[], nnx.Module],
    loss_fn: LossFn,
    get_batch: Callable[[np.ndarray], Any],
    n_train: int,
    cfg: TrainConfig,
    out: Path,
    meta: dict[str, Any],
    sample: Callable[[nnx.Module, int], None] | None = None,
    progress: bool = True,
    max_seconds: float | None = None,
) -> nnx.Module:
    """Train the module `build()` makes for `cfg.steps` steps and return it.

    `get_batch(indices)` gathers a batch of host arrays (passed to the jitted step
    as arguments, so the data set is never baked into the compiled program);
    `loss_fn(model, batch, key)` scores it.  `max_seconds` stops the run early (with a
    checkpoint and a sample) once that much wall time has passed: a fixed time budget
    without changing the schedule; rerunning resumes.  Resumes from `out/checkpoints` when it
    holds a step, after checking that its kind and model config equal `meta`'s."""
    out.mkdir(parents=True, exist_ok=True)
    tx = optimizer(cfg)
    ckpts = Checkpoints(out / "checkpoints")
    start = ckpts.latest_step() or 0
    if start:
        expect = {k: meta[k] for k in ("kind", "model")}
        ckpts.check(expect)  # before building anything: a mismatch fails at once
        graphdef, params = nnx.split(abstract(build))
        templates = {"params": params, "opt_state": jax.eval_shape(tx.init, params)}
        trees, _ = ckpts.restore(templates, expect)
        params, opt_state = trees["params"], trees["opt_state"]
        print(f"resuming {out} from step {start}", file=sys.stderr)
    else:
        graphdef, params = nnx.split(create(build))
        opt_state = tx.init(params)
    _truncate_log(out / "log.jsonl", start)
    (out / "config.json").write_text(json.dumps({**meta, "train": to_dict(cfg)}, indent=2))

    step_fn = make_step(graphdef, tx, loss_fn)
    base_key = jax.random.key(cfg.seed)
    bar = _progress(start, cfg.steps, progress)
    t0, losses = time.perf_counter(), []
    with open(out / "log.jsonl", "a") as log:
        for step in range(start, cfg.steps):
            batch = get_batch(batch_indices(cfg, n_train, step))
            params, opt_state, loss = step_fn(
                params, opt_state, batch, jax.random.fold_in(base_key, step)
            )
            losses.append(loss)
            done = step + 1
            out_of_time = max_seconds is not None and time.perf_counter() - t0 > max_seconds
            if out_of_time:
                print(f"stopping at step {done} of {cfg.steps}: --max-seconds {max_seconds:g} "
                      f"reached; rerun to resume", file=sys.stderr)
            last = done == cfg.steps or out_of_time
            if done % cfg.log_every == 0 or last:
                mean = float(np.mean(jax.device_get(losses)))
                losses = []
                rec = {"step": done, "loss": mean, "seconds": round(time.perf_counter() - t0, 2)}
                log.write(json.dumps(rec) + "\n")
                log.flush()
                bar.update(done, mean)
            if done % cfg.ckpt_every == 0 or last:
                ckpts.save(done, {"params": params, "opt_state": opt_state}, meta)
            if sample is not None and (
                (cfg.sample_every and done % cfg.sample_every == 0) or last
            ):
                sample(nnx.merge(graphdef, params), done)
            if out_of_time:
                break
    bar.close()
    return nnx.merge(graphdef, params)


def _truncate_log(path: Path, step: int) -> None:
    """Drop log lines past the checkpoint a run resumes from (written before a crash)."""
    if not path.exists():
        return
    keep = [
        line for line in path.read_text().splitlines() if line and json.loads(line)["step"] <= step
    ]
    tmp = path.with_suffix(".tmp")
    tmp.write_text("".join(line + "\n" for line in keep))
    tmp.replace(path)


class _progress:
    """tqdm if installed, else one line per log interval."""

    def __init__(self, start: int, total: int, enabled: bool):
        self.bar = None
        self.enabled = enabled
        if enabled:
            try:
                from tqdm import tqdm

                self.bar = tqdm(total=total, initial=start, unit="step", dynamic_ncols=True)
            except ImportError:
                pass
        self.last = start

    def update(self, step: int, loss: float) -> None:
        if self.bar is not None:
            self.bar.update(step - self.last)
            self.bar.set_postfix(loss=f"{loss:.4f}")
        elif self.enabled:
            print(f"step {step} loss {loss:.4f}", file=sys.stderr)
        self.last = step

    def close(self) -> None:
        if self.bar is not None:
            self.bar.close()


# ---- data and CLI pieces shared by the entry points ----


def run_parser(prog: str, doc: str | None) -> argparse.ArgumentParser:
    """The parser every training entry point starts from: --out, the run directory."""
    p = argparse.ArgumentParser(prog=prog, description=doc,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument(
        "--out",
        type=Path,
        required=True,
        help="run directory: checkpoints/, log.jsonl, samples/, config.json; resumes if it holds checkpoints",
    )
    return p


def add_data_flags(parser: argparse.ArgumentParser, training: bool = True) -> None:
    """--bank / --data / --synthetic (and, for training, --preset, --quick and --no-progress)."""
    g = parser.add_argument_group("data (one of --bank, --data, --synthetic)")
    g.add_argument(
        "--bank",
        type=Path,
        help="demonstration bank directory (python -m agnostos_mjx.data.generate)",
    )
    g.add_argument(
        "--camera",
        default="front",
        help="bank camera whose frames to use (default front, as X-ICM)",
    )
    g.add_argument(
        "--data", type=Path, help="a FramePairs .npz (FramePairs.save) instead of a bank"
    )
    g.add_argument(
        "--synthetic",
        type=int,
        metavar="N",
        help="N synthetic moving-square demos instead (smoke tests)",
    )
    if not training:
        return
    g = parser.add_argument_group("run")
    g.add_argument(
        "--preset",
        choices=tuple(PRESETS),
        default="default",
        help="model and training sizes: 'default' (the shipped model: 14.7 M parameters, "
        "docs/performance.md has its training time), 'large' (a 45 M-parameter model, 2.4x slower, too big "
        "to ship) or 'quick' (CPU smoke run); single flags below override it",
    )
    g.add_argument(
        "--quick",
        action="store_true",
        help="same as --preset quick: tiny widths, 20 steps, 8 DDIM steps: a CPU smoke run",
    )
    g.add_argument(
        "--no-progress", action="store_true", help="no progress bar (losses still go to log.jsonl)"
    )


def preset(args: argparse.Namespace) -> Preset:
    """The configs named by --preset (or --quick)."""
    if args.quick and args.preset not in ("default", "quick"):
        raise SystemExit(f"--quick and --preset {args.preset} contradict each other")
    return PRESETS["quick" if args.quick else args.preset]


def load_data(args: argparse.Namespace) -> FramePairs:
    if args.bank is not None:
        return FramePairs.from_bank(args.bank, args.camera)
    if args.data is not None:
        if not args.data.exists():
            raise SystemExit(f"--data {args.data}: no such file")
        return FramePairs.load(args.data)
    if args.synthetic:
        return synthetic(args.synthetic)
    raise SystemExit("give --bank DIR, --data PATH.npz or --synthetic N")


def save_grid(path: Path, columns: list[np.ndarray], titles: list[str]) -> Path | None:
    """Save uint8 image sets (each (N,H,W,3)) as one PNG grid, one column per set,
    with the titles in a .txt beside it.  A failed write warns instead of stopping training."""
    gap = ((0, 2), (0, 2), (0, 0))  # white lines between images
    cols = [np.concatenate([np.pad(im, gap, constant_values=255) for im in c]) for c in columns]
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_bytes(png_bytes(np.concatenate(cols, axis=1)))
        path.with_suffix(".txt").write_text(" | ".join(titles) + "\n")
    except OSError as err:
        print(f"sample grid {path} not written: {err}", file=sys.stderr)
        return None
    return path


def png_bytes(rgb: np.ndarray) -> bytes:
    """Encode an (H, W, 3) uint8 image as PNG with numpy + zlib only (no PIL needed)."""
    h, w, _ = rgb.shape
    raw = np.concatenate([np.zeros((h, 1), np.uint8), rgb.reshape(h, 3 * w)], axis=1)  # filter 0

    def chunk(kind: bytes, data: bytes) -> bytes:
        body = kind + data
        return struct.pack(">I", len(data)) + body + struct.pack(">I", zlib.crc32(body))

    header = struct.pack(">IIBBBBB", w, h, 8, 2, 0, 0, 0)  # 8-bit RGB
    return (
        b"\x89PNG\r\n\x1a\n"
        + chunk(b"IHDR", header)
        + chunk(b"IDAT", zlib.compress(raw.tobytes()))
        + chunk(b"IEND", b"")
    )
