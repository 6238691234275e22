"""Stage 1: train the KL autoencoder on first and last frames of the training demos.

python -m agnostos_mjx.train.autoencoder --bank BANK --out runs/ae
python -m agnostos_mjx.train.autoencoder --bank BANK --out runs/ae
python -m agnostos_mjx.train.autoencoder --synthetic 64 --quick --out /tmp/ae
"""

from __future__ import annotations

import argparse
from pathlib import Path

import jax
import numpy as np
from flax import nnx

from agnostos_mjx.dynamics.autoencoder import Autoencoder, autoencoder_loss, to_uint8
from agnostos_mjx.dynamics.config import (
    AE_DEFAULT,
    AE_QUICK,
    AE_TRAIN_DEFAULT,
    TRAIN_QUICK,
    AutoencoderConfig,
    TrainConfig,
    add_flags,
    apply_flags,
)
from agnostos_mjx.dynamics.data import FramePairs
from agnostos_mjx.dynamics.pipeline import autoencoder_meta
from agnostos_mjx.infra.settings import configure_jax
from agnostos_mjx.train.common import (
    add_data_flags,
    load_data,
    preset,
    run_parser,
    save_grid,
    train,
)


def train_autoencoder(
    pairs: FramePairs, cfg: AutoencoderConfig, tcfg: TrainConfig, out: Path, progress: bool = True
) -> Autoencoder:
    """Train (or resume) an autoencoder run in `out`; held-out demos only appear in sample grids."""
    train_set, held = pairs.split(tcfg.holdout_every)
    frames = np.concatenate([train_set.first, train_set.last])
    shown = np.concatenate([held.first[:4], held.last[:4]]) if len(held) else frames[:8]

    @nnx.jit
    def reconstruct(model: Autoencoder, x: jax.Array) -> jax.Array:
        return to_uint8(model.decode(model.encode(x)[0]))

    def sample(model: Autoencoder, step: int) -> None:
        save_grid(
            out / "samples" / f"step_{step:07d}.png",
            [shown, np.asarray(reconstruct(model, shown))],
            ["frame", "reconstruction"],
        )

    return train(
        lambda: Autoencoder(cfg, rngs=nnx.Rngs(tcfg.seed)),
        lambda m, batch, key: autoencoder_loss(m, batch, key, cfg.kl_weight),
        lambda idx: frames[idx],
        len(frames),
        tcfg,
        out,
        autoencoder_meta(cfg),
        sample,
        progress,
    )


def parser() -> argparse.ArgumentParser:
    p = run_parser("python -m agnostos_mjx.train.autoencoder", __doc__)
    add_data_flags(p)
    add_flags(p, "ae", AE_DEFAULT, AE_QUICK)
    add_flags(p, "train", AE_TRAIN_DEFAULT, TRAIN_QUICK)
    return p


def main(argv: list[str] | None = None) -> None:
    configure_jax()
    args = parser().parse_args(argv)
    chosen = preset(args)
    cfg = apply_flags(args, "ae", chosen.ae)
    tcfg = apply_flags(args, "train", chosen.ae_train)
    train_autoencoder(load_data(args), cfg, tcfg, args.out, progress=not args.no_progress)
    print(f"autoencoder run in {args.out}")


if __name__ == "__main__":
    main()
