"""The shipping format of a trained dynamics model: what feature extraction needs, small.

An export is a directory of two files:

  params.npz   - one compressed .npz of float16 arrays: the autoencoder's ENCODER
                 ("ae.encoder..."), the text encoder and the UNet ("dynamics...");
                 the decoder and the optimiser state are left out;
  export.json  - format name and version, the model configs, the sampling settings,
                 the latent scale, where the weights came from, and params.npz's SHA-256.

Each file is written under a temporary name and renamed into place, params.npz
first; the SHA-256 in export.json binds the pair, so a reader never accepts a
half-written or mismatched export.  `Pipeline.load(directory)` reads an export
as it reads a training run (weights cast back to float32).
"""

from __future__ import annotations

import functools
import hashlib
import json
import math
import os
import tempfile
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path
from typing import Any

import jax
import numpy as np
from flax import nnx

from agnostos_mjx.dynamics.autoencoder import Autoencoder
from agnostos_mjx.dynamics.checkpoint import CheckpointError, flatten, read_meta, unflatten
from agnostos_mjx.dynamics.config import (
    AutoencoderConfig,
    DiffusionConfig,
    TextConfig,
    UNetConfig,
    from_dict,
    to_dict,
)
from agnostos_mjx.dynamics.diffusion import DynamicsModel
from agnostos_mjx.dynamics.layers import abstract

FORMAT = "agnostos_mjx.dynamics.export"
VERSION = 1
PARAMS_FILE, META_FILE = "params.npz", "export.json"
FLOAT16_MAX = float(np.finfo(np.float16).max)
_NPZ_OVERHEAD = 512  # bytes per array, generous: .npy header + two zip entry headers


def is_export(path: str | Path) -> bool:
    """Whether `path` looks like an export (rather than a training run directory)."""
    return (Path(path) / META_FILE).exists() or (Path(path) / PARAMS_FILE).exists()


def feature_modules(
    ae: AutoencoderConfig, text: TextConfig, unet: UNetConfig
) -> dict[str, nnx.Module]:
    """Abstract (shape-only) modules of exactly what an export holds, by array prefix."""
    return {
        "ae": abstract(lambda: Autoencoder(ae, decoder=False, rngs=nnx.Rngs(0))),
        "dynamics": abstract(lambda: DynamicsModel(text, unet, rngs=nnx.Rngs(0))),
    }


@functools.cache
def _sizes(ae: AutoencoderConfig, text: TextConfig, unet: UNetConfig) -> tuple[int, ...]:
    """Element count of every array an export of these configs holds (from shapes alone;
    tracing a default-sized model takes seconds on CPU, hence the cache)."""
    modules = feature_modules(ae, text, unet)
    return tuple(
        math.prod(x.shape) for m in modules.values() for x in jax.tree.leaves(nnx.state(m))
    )


def parameter_count(ae: AutoencoderConfig, text: TextConfig, unet: UNetConfig) -> int:
    """Parameters an export of these configs holds (computed from shapes, nothing built)."""
    return sum(_sizes(ae, text, unet))


def size_bound(ae: AutoencoderConfig, text: TextConfig, unet: UNetConfig) -> int:
    """An upper bound on params.npz's size in bytes: 2 bytes per parameter plus a
    generous per-array overhead (compression only ever saves on trained weights)."""
    return sum(2 * n + _NPZ_OVERHEAD for n in _sizes(ae, text, unet))


def export(run: str | Path, out: str | Path, ae_run: str | Path | None = None) -> dict[str, Any]:
    """Write the export of dynamics run `run` (and its autoencoder, or `ae_run`) to
    directory `out`; returns the metadata written to export.json."""
    from agnostos_mjx.dynamics.pipeline import Pipeline

    run, out = Path(run), Path(out)
    if is_export(run):
        raise CheckpointError(f"{run} is already an export; give a training run directory")
    pipe = Pipeline.load(run, ae_run)
    meta = read_meta(run)
    ae_dir = Path(ae_run or meta["autoencoder_dir"])
    arrays = {
        **flatten(nnx.state(pipe.ae.encoder), "ae.encoder"),
        **flatten(nnx.state(pipe.model), "dynamics"),
    }
    params = {}
    for name, value in arrays.items():
        value = np.asarray(value)
        if np.issubdtype(value.dtype, np.floating):
            peak = float(np.max(np.abs(value))) if value.size else 0.0
            if not np.isfinite(peak) or peak > FLOAT16_MAX:
                raise CheckpointError(f"{run}: {name} has |value| {peak:g}, not float16-safe")
            value = value.astype(np.float16)
        params[name] = value

    out.mkdir(parents=True, exist_ok=True)
    _write_atomic(out / PARAMS_FILE, lambda f: np.savez_compressed(f, **params))
    info = {
        "format": FORMAT,
        "version": VERSION,
        "model": meta["model"],
        "diffusion": meta["diffusion"],
        "latent_scale": meta["latent_scale"],
        "parameters": int(sum(v.size for v in params.values())),
        "sha256": _sha256(out / PARAMS_FILE),
        "source": {
            "run": str(run.absolute()),
            "step": meta["step"],
            "autoencoder_run": str(ae_dir.absolute()),
            "autoencoder_step": read_meta(ae_dir)["step"],
        },
    }
    text = json.dumps(info, indent=2) + "\n"
    _write_atomic(out / META_FILE, lambda f: f.write(text.encode()))
    return info


def read_export(path: str | Path) -> tuple[dict[str, Any], dict[str, np.ndarray]]:
    """The metadata and float16 arrays of an export, checked: CheckpointError naming
    the path if a file is missing, corrupt or of another format version."""
    path = Path(path)
    meta_path, params_path = path / META_FILE, path / PARAMS_FILE
    for p in (meta_path, params_path):
        if not p.exists():
            raise CheckpointError(f"export {path} is incomplete: no {p.name}")
    try:
        meta = json.loads(meta_path.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as err:
        raise CheckpointError(f"export {meta_path} is corrupt: {err}") from err
    if not isinstance(meta, dict) or meta.get("format") != FORMAT:
        raise CheckpointError(f"{meta_path} is not a dynamics export (format != {FORMAT!r})")
    if meta.get("version") != VERSION:
        raise CheckpointError(
            f"export {path} has format version {meta.get('version')!r}, this code reads "
            f"{VERSION}; export it again with python -m agnostos_mjx.train.export"
        )
    if _sha256(params_path) != meta.get("sha256"):
        raise CheckpointError(
            f"export {params_path} is corrupt or does not belong to its {META_FILE} "
            "(SHA-256 differs); export it again"
        )
    try:
        with np.load(params_path, allow_pickle=False) as z:
            arrays = {k: z[k] for k in z.files}
    except Exception as err:  # zipfile, zlib and format errors alike
        raise CheckpointError(f"export {params_path} cannot be read: {err}") from err
    return meta, arrays


def load_export(path: str | Path, chunk: int | None = None, **sampling: Any):
    """A feature-extraction `Pipeline` from an export directory (float32 weights, no
    decoder).  `sampling` overrides sampling fields, as in `Pipeline.load`."""
    from agnostos_mjx.dynamics.pipeline import Pipeline

    path = Path(path)
    meta, arrays = read_export(path)
    try:
        m = meta["model"]
        ae_cfg = from_dict(AutoencoderConfig, m["autoencoder"])
        text, unet = from_dict(TextConfig, m["text"]), from_dict(UNetConfig, m["unet"])
        diffusion = replace(from_dict(DiffusionConfig, meta["diffusion"]), **sampling)
        scale = float(meta["latent_scale"])
    except (KeyError, TypeError, ValueError) as err:
        raise CheckpointError(f"export {path} has incompatible configs: {err!r}") from err
    for k in ("prediction", "schedule", "timesteps"):
        if m.get(k) != to_dict(diffusion)[k]:
            raise CheckpointError(f"export {path}: model.{k} {m.get(k)!r} != diffusion.{k}")
    arrays = {k: v.astype(np.float32) if v.dtype == np.float16 else v for k, v in arrays.items()}
    modules = feature_modules(ae_cfg, text, unet)
    extra = sorted(k for k in arrays if not k.startswith(("ae.", "dynamics.")))
    if extra:
        raise CheckpointError(f"export {path} does not fit the model: unexpected {extra[:5]}")
    ae, model = (_fill(modules[name], arrays, name, path) for name in ("ae", "dynamics"))
    identity = f"{path.absolute()}@export-v{VERSION}:{meta['sha256'][:16]}|{to_dict(diffusion)}"
    return Pipeline(ae, scale, model, text, diffusion, chunk, identity)


def _fill(module: nnx.Module, arrays: dict[str, np.ndarray], prefix: str, where: Path):
    graphdef, state = nnx.split(module)
    return nnx.merge(graphdef, unflatten(state, arrays, prefix, where / PARAMS_FILE))


def _sha256(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def _write_atomic(path: Path, write: Callable[[Any], None]) -> None:
    """Write through `write(file)` to a temporary file beside `path`, then rename it."""
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        with os.fdopen(fd, "wb") as f:
            write(f)
            f.flush()
            os.fsync(f.fileno())
        os.chmod(tmp, 0o644)  # mkstemp's 0600 would keep other users from reading the model
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
