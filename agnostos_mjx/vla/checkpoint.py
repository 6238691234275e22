"""Reference VLA run directories and exports: what they hold and how a policy loads one.

A run directory (``python -m agnostos_mjx.train.vla --out RUN``) holds
``checkpoints/<step>/`` (orbax, dynamics/checkpoint.py: flat float32 arrays under their
parameter paths, ``params.*`` and ``opt_state.*``, plus JSON metadata), ``config.json``,
``log.jsonl`` (training loss) and ``heldout.jsonl`` (held-out keyframe accuracy).  The
metadata names the kind (``reference-vla``), the model config (model.VLAConfig) and the
observation the model was trained on (cameras and image size), which the policy
declares as its ObservationSpec.

An export (``train.vla --out RUN --export DIR``) is what travels and ships: ``params.npz``
(the parameters as float16, compressed; no optimiser state: ~13 MB at the default sizes
instead of ~80 MB) and ``vla.json`` (the same metadata, the source run and step, and the
SHA-256 of params.npz).  `load` reads either.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np
from flax import nnx

from agnostos_mjx.dynamics.checkpoint import (
    CheckpointError,
    flatten,
    load_params,
    read_meta,
    unflatten,
)
from agnostos_mjx.dynamics.config import from_dict, to_dict
from agnostos_mjx.dynamics.export import float16_arrays, write_atomic
from agnostos_mjx.dynamics.export_format import sha256
from agnostos_mjx.dynamics.layers import abstract
from agnostos_mjx.vla.model import ReferenceVLA, VLAConfig

KIND = "reference-vla"
EXPORT_VERSION = 1
PARAMS_FILE, META_FILE = "params.npz", "vla.json"


def run_meta(cfg: VLAConfig, cameras: tuple[str, ...], size: int) -> dict[str, Any]:
    """The metadata every checkpoint of a run carries (train.common.train checks "kind"
    and "model" when resuming)."""
    return {"kind": KIND, "model": to_dict(cfg),
            "observation": {"cameras": list(cameras), "size": int(size)}}


def _abstract_model(meta: dict[str, Any], where: Path) -> ReferenceVLA:
    if meta.get("kind") != KIND:
        raise CheckpointError(f"{where} holds a {meta.get('kind')!r} model, not {KIND!r}")
    try:
        cfg = from_dict(VLAConfig, meta["model"])
    except (KeyError, TypeError, ValueError) as err:
        raise CheckpointError(f"{where}: incompatible model config: {err!r}") from err
    return abstract(lambda: ReferenceVLA(cfg, rngs=nnx.Rngs(0)))


def load(path: str | Path) -> tuple[ReferenceVLA, dict[str, Any]]:
    """The model of a run directory's latest checkpoint, or of an export, and its
    metadata; anything missing, damaged or foreign raises CheckpointError naming the path."""
    path = Path(path)
    if (path / META_FILE).exists():
        return _load_export(path)
    meta = read_meta(path)
    model = _abstract_model(meta, path)
    return load_params(path, model, {"kind": KIND, "model": meta["model"]}), meta


def export(run: str | Path, out: str | Path) -> dict[str, Any]:
    """Write the float16 export of run directory `run`'s latest checkpoint to `out`;
    returns the metadata written to vla.json."""
    run, out = Path(run), Path(out)
    model, meta = load(run)
    params = float16_arrays(flatten(nnx.split(model)[1], "params"), run)
    out.mkdir(parents=True, exist_ok=True)
    write_atomic(out / PARAMS_FILE, lambda f: np.savez_compressed(f, **params))
    info = {**{k: v for k, v in meta.items() if k != "step"}, "version": EXPORT_VERSION,
            "parameters": int(sum(v.size for v in params.values())),
            "sha256": sha256(out / PARAMS_FILE),
            "source": {"run": str(run.absolute()), "step": meta.get("step")}}
    text = json.dumps(info, indent=1) + "\n"
    write_atomic(out / META_FILE, lambda f: f.write(text.encode()))
    return info


def _load_export(path: Path) -> tuple[ReferenceVLA, dict[str, Any]]:
    params_path = path / PARAMS_FILE
    try:
        meta = json.loads((path / META_FILE).read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as err:
        raise CheckpointError(f"export {path / META_FILE} is corrupt: {err}") from err
    if meta.get("version") != EXPORT_VERSION:
        raise CheckpointError(f"export {path} has version {meta.get('version')!r}, this "
                              f"code reads {EXPORT_VERSION}")
    if not params_path.exists() or sha256(params_path) != meta.get("sha256"):
        raise CheckpointError(f"export {params_path} is missing, corrupt or not the one "
                              f"{META_FILE} names (SHA-256)")
    model = _abstract_model(meta, path)
    with np.load(params_path, allow_pickle=False) as z:
        arrays = {k: z[k].astype(np.float32) if z[k].dtype == np.float16 else z[k]
                  for k in z.files}
    graphdef, state = nnx.split(model)  # the state load_params fills from a run
    return nnx.merge(graphdef, unflatten(state, arrays, "params", params_path)), meta
