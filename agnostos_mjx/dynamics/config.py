"""Frozen configs for the dynamics diffusion model, with `default` (shipped), `large` and `quick` presets.

Every field carries its own help text so the training CLIs can expose each one
as a flag (`--batch-size 64`) without a second list of descriptions.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
from dataclasses import dataclass, field, fields, replace
from typing import Any

FRAME_SIZE = 128  # RLBench front-camera frames are 128 x 128 (X-ICM issue #3).
LATENT_SIZE = 16  # 128 / 2**3: three downsamplings give 16 x 16 x 4 = 1,024 values.
LATENT_CHANNELS = 4
FEATURE_DIM = LATENT_SIZE * LATENT_SIZE * LATENT_CHANNELS  # 1,024, as in the original.


def _f(default: Any, help: str) -> Any:
    return field(default=default, metadata={"help": help})


@dataclass(frozen=True)
class AutoencoderConfig:
    """KL autoencoder: 128x128x3 frames <-> 16x16x4 latents."""

    channels: tuple[int, ...] = _f(
        (32, 64, 128, 256), "channels per resolution level (4 levels: 128, 64, 32, 16 px)"
    )
    blocks: int = _f(1, "residual blocks per level")
    groups: int = _f(32, "GroupNorm groups (must divide every channel count)")
    kl_weight: float = _f(
        1e-4, "weight of the KL term against the per-pixel L1 reconstruction loss"
    )


@dataclass(frozen=True)
class TextConfig:
    """Byte-level bidirectional transformer: any word, seen or not, has tokens."""

    width: int = _f(192, "token width")
    depth: int = _f(4, "transformer layers")
    heads: int = _f(4, "attention heads")
    max_len: int = _f(96, "bytes per instruction incl. the leading [CLS]; longer ones are cut")


@dataclass(frozen=True)
class UNetConfig:
    """UNet over 16x16 latents; input = noisy target latent ++ first-frame latent (8 ch)."""

    channels: tuple[int, ...] = _f((64, 128, 128), "channels per level (16, 8, 4 px)")
    blocks: int = _f(2, "residual blocks per level")
    attention: tuple[bool, ...] = _f(
        (True, True, True), "self+cross attention after each block, per level"
    )
    heads: int = _f(4, "attention heads")
    groups: int = _f(32, "GroupNorm groups")


@dataclass(frozen=True)
class DiffusionConfig:
    """Noise schedule, parameterisation, conditioning dropout and DDIM sampling."""

    prediction: str = _f("v", "what the UNet predicts: 'v' or 'epsilon'")
    schedule: str = _f("cosine", "noise schedule: 'cosine' or 'scaled_linear'")
    timesteps: int = _f(1000, "training timesteps")
    drop_text: float = _f(0.05, "training probability of dropping only the instruction")
    drop_image: float = _f(0.05, "training probability of dropping only the first frame")
    drop_both: float = _f(0.05, "training probability of dropping both (unconditional)")
    sample_steps: int = _f(50, "DDIM steps at sampling (the original uses 50)")
    image_guidance: float = _f(2.5, "classifier-free guidance scale on the first frame")
    text_guidance: float = _f(2.5, "classifier-free guidance scale on the instruction")
    sample_seed: int = _f(
        123, "seed of the initial sampling noise (the same noise for every query)"
    )


@dataclass(frozen=True)
class TrainConfig:
    """Optimiser, schedule, logging and checkpoint cadence of one training run."""

    steps: int = _f(20_000, "total optimiser steps (resuming continues up to this count)")
    batch_size: int = _f(64, "examples per step")
    lr: float = _f(2e-4, "peak learning rate of AdamW")
    warmup: int = _f(500, "linear warm-up steps before the cosine decay")
    weight_decay: float = _f(0.01, "AdamW weight decay")
    grad_clip: float = _f(1.0, "global gradient-norm clip")
    holdout_every: int = _f(10, "demo i is held out when i % holdout_every == holdout_every - 1")
    log_every: int = _f(50, "steps between JSONL loss lines")
    sample_every: int = _f(2_000, "steps between PNG sample grids (0: only at the end)")
    ckpt_every: int = _f(1_000, "steps between checkpoints (and one at the end)")
    seed: int = _f(0, "seed of initialisation, batches and noise")


AE_DEFAULT = AutoencoderConfig()
AE_QUICK = AutoencoderConfig(channels=(8, 16, 16, 16), blocks=1, groups=4)
TEXT_QUICK = TextConfig(width=32, depth=1, heads=2, max_len=64)
UNET_QUICK = UNetConfig(channels=(16, 32), blocks=1, attention=(False, True), heads=2, groups=4)
DIFFUSION_DEFAULT = DiffusionConfig()
# Fewer DDIM steps keep CPU tests fast; the schedule and guidance stay the real ones.
DIFFUSION_QUICK = DiffusionConfig(sample_steps=8)
# Training lengths for the ~3,600-demo seen bank: ~22 AE epochs; ~125 UNet epochs for the
# default (shipped) model (its training rate: docs/performance.md).
AE_TRAIN_DEFAULT = TrainConfig(steps=6_000, batch_size=32, lr=2e-4, warmup=300)
DYN_TRAIN_DEFAULT = TrainConfig(steps=7_000, batch_size=64, lr=2e-4, warmup=500)
DYN_TRAIN_LARGE = TrainConfig(steps=15_000, batch_size=64, lr=2e-4, warmup=500)
TRAIN_QUICK = TrainConfig(
    steps=20, batch_size=4, lr=1e-3, warmup=0, log_every=5, sample_every=0, ckpt_every=10
)

# The default model is sized to ship inside the package: the float16 export (autoencoder
# encoder 2.6 M + text 2.0 M + UNet 10.1 M = 14.7 M parameters) is 27.3 MB.  `large` is the
# wider model first measured (UNet 38.7 M, text 3.5 M); its export would be ~90 MB.
TEXT_LARGE = TextConfig(width=256)
UNET_LARGE = UNetConfig(channels=(128, 256, 256))
TEXT_DEFAULT = TextConfig()
UNET_DEFAULT = UNetConfig()


@dataclass(frozen=True)
class Preset:
    """Every config of both training stages, picked as a whole by `--preset NAME`."""

    ae: AutoencoderConfig
    text: TextConfig
    unet: UNetConfig
    diffusion: DiffusionConfig
    ae_train: TrainConfig
    dyn_train: TrainConfig


PRESETS: dict[str, Preset] = {
    "default": Preset(
        AE_DEFAULT, TEXT_DEFAULT, UNET_DEFAULT, DIFFUSION_DEFAULT, AE_TRAIN_DEFAULT, DYN_TRAIN_DEFAULT
    ),
    "large": Preset(
        AE_DEFAULT, TEXT_LARGE, UNET_LARGE, DIFFUSION_DEFAULT, AE_TRAIN_DEFAULT, DYN_TRAIN_LARGE
    ),
    "quick": Preset(AE_QUICK, TEXT_QUICK, UNET_QUICK, DIFFUSION_QUICK, TRAIN_QUICK, TRAIN_QUICK),
}


def to_dict(cfg: Any) -> dict[str, Any]:
    """JSON-friendly dict (tuples become lists) used in checkpoint metadata."""
    return json.loads(json.dumps(dataclasses.asdict(cfg)))


def from_dict(cls: type, data: dict[str, Any]) -> Any:
    """Inverse of `to_dict`; lists become tuples again."""
    return cls(**{k: tuple(v) if isinstance(v, list) else v for k, v in data.items()})


def diff(saved: dict[str, Any], current: dict[str, Any], prefix: str = "") -> list[str]:
    """Human-readable list of fields that differ between two config dicts."""
    out = []
    for key in sorted(set(saved) | set(current)):
        a, b = saved.get(key, "<missing>"), current.get(key, "<missing>")
        if isinstance(a, dict) and isinstance(b, dict):
            out += diff(a, b, f"{prefix}{key}.")
        elif a != b:
            out.append(f"{prefix}{key}: checkpoint has {a!r}, config has {b!r}")
    return out


# ---- CLI: one flag per config field, named `--<group>-<field>` or `--<field>` ----


def _bool(s: str) -> bool:
    return s.lower() in ("1", "true", "yes")


def add_flags(parser: argparse.ArgumentParser, group: str, default: Any, quick: Any) -> None:
    """Add one flag per field of the config `default` (a preset instance); the
    help shows the default and the --quick values.  Flags default to None, so
    `apply_flags` changes only what was given."""
    cls = type(default)
    g = parser.add_argument_group(f"{group} ({cls.__name__})", cls.__doc__)
    for f in fields(cls):
        flag = f"--{f.name}" if group == "train" else f"--{group}-{f.name}"
        value, quick_value = getattr(default, f.name), getattr(quick, f.name)
        help = f"{f.metadata['help']} (default {value!r}; --quick {quick_value!r})"
        kw: dict[str, Any] = {"default": None, "help": help.replace("%", "%%")}
        if isinstance(value, tuple):
            kw.update(nargs="+", type=_bool if isinstance(value[0], bool) else type(value[0]))
        else:
            kw.update(type=_bool if isinstance(value, bool) else type(value))
        g.add_argument(
            flag.replace("_", "-"), dest=f"{group}__{f.name}", metavar=f.name.upper(), **kw
        )


def apply_flags(args: argparse.Namespace, group: str, cfg: Any) -> Any:
    """Return `cfg` with every flag of `group` that was given on the command line."""
    given = {}
    for f in fields(cfg):
        value = getattr(args, f"{group}__{f.name}", None)
        if value is not None:
            given[f.name] = tuple(value) if isinstance(value, list) else value
    return replace(cfg, **given)
