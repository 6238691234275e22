"""Stage 2: train the dynamics diffusion model (text encoder + UNet) in the latent
space of a trained autoencoder: predict each demo's last frame from its first
frame and instruction.

    python -m agnostos_mjx.train.dynamics --bank BANK --ae runs/ae --out runs/dyn
    python -m agnostos_mjx.train.dynamics --bank BANK --ae runs/ae --out runs/dyn
    python -m agnostos_mjx.train.dynamics --synthetic 64 --quick --ae /tmp/ae --out /tmp/dyn
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
from flax import nnx

from agnostos_mjx.dynamics.config import (
    DIFFUSION_DEFAULT,
    DIFFUSION_QUICK,
    DYN_TRAIN_DEFAULT,
    TEXT_DEFAULT,
    TEXT_QUICK,
    TRAIN_QUICK,
    UNET_DEFAULT,
    UNET_QUICK,
    DiffusionConfig,
    TextConfig,
    TrainConfig,
    UNetConfig,
    add_flags,
    apply_flags,
)
from agnostos_mjx.dynamics.data import FramePairs
from agnostos_mjx.dynamics.diffusion import DynamicsModel, diffusion_loss
from agnostos_mjx.dynamics.pipeline import Pipeline, dynamics_meta, load_autoencoder
from agnostos_mjx.dynamics.text import tokenize
from agnostos_mjx.infra.settings import configure_jax
from agnostos_mjx.train.common import (
    add_data_flags,
    load_data,
    preset,
    run_parser,
    save_grid,
    train,
)


def train_dynamics(
    pairs: FramePairs,
    ae_run: Path,
    text: TextConfig,
    unet: UNetConfig,
    diffusion: DiffusionConfig,
    tcfg: TrainConfig,
    out: Path,
    progress: bool = True,
) -> Pipeline:
    """Train (or resume) a dynamics run in `out` on the autoencoder of `ae_run`.

    All frames are encoded once up front (the autoencoder is frozen), so a step
    touches only 16x16 latents.  latent_scale = 1 / std of the training latents
    gives the diffusion model unit-variance data, like SD's 0.18215."""
    ae, ae_cfg = load_autoencoder(ae_run)
    train_set, held = pairs.split(tcfg.holdout_every)
    raw = Pipeline(ae, 1.0)
    z_first, z_last = raw.encode(train_set.first), raw.encode(train_set.last)
    scale = float(1.0 / np.std(np.concatenate([z_first, z_last])))
    z_first, z_last = z_first * scale, z_last * scale
    ids, mask = tokenize(train_set.instructions, text.max_len)

    meta = dynamics_meta(text, unet, diffusion, ae_cfg)
    meta.update(latent_scale=scale, autoencoder_dir=str(Path(ae_run).absolute()))
    shown = held if len(held) else train_set
    shown = shown.subset(np.arange(min(6, len(shown))))

    def sample(model: DynamicsModel, step: int) -> None:
        pipe = Pipeline(ae, scale, model, text, diffusion)
        pred = pipe.decode(pipe.predict(pipe.encode(shown.first), shown.instructions))
        save_grid(
            out / "samples" / f"step_{step:07d}.png",
            [shown.first, pred, shown.last],
            ["first frame", "predicted last", "true last"] + shown.instructions,
        )

    trained = train(
        lambda: DynamicsModel(text, unet, rngs=nnx.Rngs(tcfg.seed)),
        lambda m, b, key: diffusion_loss(m, diffusion, *b, key),
        lambda idx: (z_first[idx], z_last[idx], ids[idx], mask[idx]),
        len(z_first),
        tcfg,
        out,
        meta,
        sample,
        progress,
    )
    return Pipeline(ae, scale, trained, text, diffusion)


def parser() -> argparse.ArgumentParser:
    p = run_parser("python -m agnostos_mjx.train.dynamics", __doc__)
    p.add_argument(
        "--ae",
        type=Path,
        required=True,
        help="run directory of a trained autoencoder (python -m agnostos_mjx.train.autoencoder)",
    )
    add_data_flags(p)
    add_flags(p, "text", TEXT_DEFAULT, TEXT_QUICK)
    add_flags(p, "unet", UNET_DEFAULT, UNET_QUICK)
    add_flags(p, "diffusion", DIFFUSION_DEFAULT, DIFFUSION_QUICK)
    add_flags(p, "train", DYN_TRAIN_DEFAULT, TRAIN_QUICK)
    return p


def main(argv: list[str] | None = None) -> None:
    configure_jax()
    args = parser().parse_args(argv)
    chosen = preset(args)
    text = apply_flags(args, "text", chosen.text)
    unet = apply_flags(args, "unet", chosen.unet)
    diffusion = apply_flags(args, "diffusion", chosen.diffusion)
    tcfg = apply_flags(args, "train", chosen.dyn_train)
    train_dynamics(
        load_data(args),
        args.ae,
        text,
        unet,
        diffusion,
        tcfg,
        args.out,
        progress=not args.no_progress,
    )
    print(f"dynamics run in {args.out}")


if __name__ == "__main__":
    main()
