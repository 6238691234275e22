"""Reference VLA run directories: what a checkpoint holds and how a policy loads one.

A run directory (``python -m agnostos_mjx.train.vla --out RUN``) holds
``checkpoints/<step>/`` (orbax, dynamics/checkpoint.py: flat float32 arrays under their
parameter paths, ``params.*`` and ``opt_state.*``, plus JSON metadata), ``config.json``,
``log.jsonl`` (training loss) and ``heldout.jsonl`` (held-out keyframe accuracy).  The
metadata names the kind (``reference-vla``), the model config (model.VLAConfig) and the
observation the model was trained on (cameras and image size), which the policy
declares as its ObservationSpec.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from flax import nnx

from agnostos_mjx.dynamics.checkpoint import CheckpointError, load_params, read_meta
from agnostos_mjx.dynamics.config import from_dict, to_dict
from agnostos_mjx.dynamics.layers import abstract
from agnostos_mjx.vla.model import ReferenceVLA, VLAConfig

KIND = "reference-vla"


def run_meta(cfg: VLAConfig, cameras: tuple[str, ...], size: int) -> dict[str, Any]:
    """The metadata every checkpoint of a run carries (train.common.train checks "kind"
    and "model" when resuming)."""
    return {"kind": KIND, "model": to_dict(cfg),
            "observation": {"cameras": list(cameras), "size": int(size)}}


def load(run: str | Path) -> tuple[ReferenceVLA, dict[str, Any]]:
    """The model of a run directory's latest checkpoint and its metadata; a missing or
    foreign run raises CheckpointError naming the path."""
    run = Path(run)
    meta = read_meta(run)
    if meta.get("kind") != KIND:
        raise CheckpointError(f"{run} holds a {meta.get('kind')!r} run, not {KIND!r}")
    cfg = from_dict(VLAConfig, meta["model"])
    model = abstract(lambda: ReferenceVLA(cfg, rngs=nnx.Rngs(0)))
    model = load_params(run, model, {"kind": KIND, "model": meta["model"]})
    return model, meta
