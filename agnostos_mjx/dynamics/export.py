"""Writing the shipping format of a trained dynamics model: what feature extraction
needs, small.  The format itself (files, version, checks, reading) is
agnostos_mjx.dynamics.export_format.

An export is a directory of params.npz (float16 encoder, text encoder and UNet) and
export.json (configs, sampling settings, latent scale, provenance, params.npz's SHA-256).
Each file is written under a temporary name and renamed into place, params.npz
first; the SHA-256 in export.json binds the pair, so a reader never accepts a
half-written or mismatched export.  `Pipeline.load(directory)` reads an export
as it reads a training run (weights cast back to float32).
"""

from __future__ import annotations

import json
import os
import tempfile
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
from flax import nnx

from agnostos_mjx.dynamics.checkpoint import CheckpointError, flatten, read_meta
from agnostos_mjx.dynamics.export_format import (
    FLOAT16_MAX,
    FORMAT,
    META_FILE,
    PARAMS_FILE,
    VERSION,
    is_export,
    sha256,
)
from agnostos_mjx.dynamics.pipeline import Pipeline


def export(run: str | Path, out: str | Path, ae_run: str | Path | None = None) -> dict[str, Any]:
    """Write the export of dynamics run `run` (and its autoencoder, or `ae_run`) to
    directory `out`; returns the metadata written to export.json."""
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
    params = float16_arrays(arrays, run)
    out.mkdir(parents=True, exist_ok=True)
    write_atomic(out / PARAMS_FILE, lambda f: np.savez_compressed(f, **params))
    info = {
        "format": FORMAT,
        "version": VERSION,
        "model": meta["model"],
        "diffusion": meta["diffusion"],
        "latent_scale": meta["latent_scale"],
        "parameters": int(sum(v.size for v in params.values())),
        "sha256": sha256(out / PARAMS_FILE),
        "source": {
            "run": str(run.absolute()),
            "step": meta["step"],
            "autoencoder_run": str(ae_dir.absolute()),
            "autoencoder_step": read_meta(ae_dir)["step"],
        },
    }
    text = json.dumps(info, indent=2) + "\n"
    write_atomic(out / META_FILE, lambda f: f.write(text.encode()))
    return info


def float16_arrays(arrays: dict[str, Any], where: str | Path) -> dict[str, np.ndarray]:
    """Floating-point arrays as float16 (others unchanged); CheckpointError naming the
    array if a value is not finite or too large for float16."""
    params = {}
    for name, value in arrays.items():
        value = np.asarray(value)
        if np.issubdtype(value.dtype, np.floating):
            peak = float(np.max(np.abs(value))) if value.size else 0.0
            if not np.isfinite(peak) or peak > FLOAT16_MAX:
                raise CheckpointError(f"{where}: {name} has |value| {peak:g}, not float16-safe")
            value = value.astype(np.float16)
        params[name] = value
    return params


def load_export(path: str | Path, chunk: int | None = None, **sampling: Any) -> Pipeline:
    """A feature-extraction `Pipeline` from an export directory (float32 weights, no
    decoder).  `sampling` overrides sampling fields, as in `Pipeline.load`."""
    return Pipeline.from_export(path, chunk, **sampling)


def write_atomic(path: Path, write: Callable[[Any], None]) -> None:
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
