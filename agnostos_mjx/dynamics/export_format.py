"""The shipping format of a trained dynamics model, read side: what an export directory
holds and how its files are checked and turned back into modules.

An export is a directory of two files:

  params.npz   - one compressed .npz of float16 arrays: the autoencoder's ENCODER
                 ("ae.encoder..."), the text encoder and the UNet ("dynamics...");
                 the decoder and the optimiser state are left out;
  export.json  - format name and version, the model configs, the sampling settings,
                 the latent scale, where the weights came from, and params.npz's SHA-256.

Writing an export (from a training run) is agnostos_mjx.dynamics.export; reading one
back as a feature `Pipeline` is `Pipeline.load` (agnostos_mjx.dynamics.pipeline), which
builds on `read_models` here.  This module imports neither, so both can import it.
"""

from __future__ import annotations

import functools
import hashlib
import json
import logging
import math
import pickle
from dataclasses import replace
from pathlib import Path
from typing import Any, NamedTuple

import flax
import jax
import numpy as np
from flax import nnx

from agnostos_mjx.dynamics.autoencoder import Autoencoder
from agnostos_mjx.dynamics.checkpoint import CheckpointError, unflatten
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
from agnostos_mjx.infra.cli import atomic_write
from agnostos_mjx.infra.settings import cache_root

FORMAT = "agnostos_mjx.dynamics.export"
VERSION = 1
PARAMS_FILE, META_FILE = "params.npz", "export.json"
FLOAT16_MAX = float(np.finfo(np.float16).max)
_NPZ_OVERHEAD = 512  # bytes per array, generous: .npy header + two zip entry headers
log = logging.getLogger(__name__)


def is_export(path: str | Path) -> bool:
    """Whether `path` looks like an export (rather than a training run directory)."""
    return (Path(path) / META_FILE).exists() or (Path(path) / PARAMS_FILE).exists()


def feature_modules(
    ae: AutoencoderConfig, text: TextConfig, unet: UNetConfig
) -> dict[str, nnx.Module]:
    """Abstract (shape-only) modules of exactly what an export holds, by array prefix.

    Tracing the constructors takes seconds in every evaluation process, so their
    structure is kept on disk (`_structure_path`) and read back in a fraction of that."""
    path = _structure_path(ae, text, unet)
    try:
        parts = pickle.loads(path.read_bytes())
        return {name: nnx.merge(*parts[name]) for name in ("ae", "dynamics")}
    except Exception:  # noqa: BLE001 - absent, half-written or from other code: rebuild
        pass
    modules = {
        "ae": abstract(lambda: Autoencoder(ae, decoder=False, rngs=nnx.Rngs(0))),
        "dynamics": abstract(lambda: DynamicsModel(text, unet, rngs=nnx.Rngs(0))),
    }
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        atomic_write(path, pickle.dumps({k: nnx.split(m) for k, m in modules.items()}))
    except OSError as err:  # a read-only cache only costs the next process the trace
        log.debug("could not keep the model structure in %s: %s", path, err)
    return modules


def _structure_path(ae: AutoencoderConfig, text: TextConfig, unet: UNetConfig) -> Path:
    """Where the abstract modules of these configs are kept: keyed by the configs, the
    versions of flax and jax, and the source of this package's dynamics modules."""
    h = hashlib.sha256(repr((to_dict(ae), to_dict(text), to_dict(unet), flax.__version__,
                             jax.__version__)).encode())
    for source in sorted(Path(__file__).parent.glob("*.py")):
        h.update(source.read_bytes())
    return cache_root() / "model_structure" / f"{h.hexdigest()[:20]}.pkl"


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
    if sha256(params_path) != meta.get("sha256"):
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


class ExportedModels(NamedTuple):
    """What an export gives a feature `Pipeline`, in its field order (less `chunk`)."""

    ae: Autoencoder
    latent_scale: float
    model: DynamicsModel
    text: TextConfig
    diffusion: DiffusionConfig
    identity: str  # path, format version, hash and sampling settings: keys cached indices


def read_models(path: str | Path, **sampling: Any) -> ExportedModels:
    """The encoder and dynamics model of an export directory (float32 weights, no
    decoder).  `sampling` overrides sampling fields, as in `Pipeline.load`."""
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
    return ExportedModels(ae, scale, model, text, diffusion, identity)


def _fill(module: nnx.Module, arrays: dict[str, np.ndarray], prefix: str, where: Path):
    graphdef, state = nnx.split(module)
    return nnx.merge(graphdef, unflatten(state, arrays, prefix, where / PARAMS_FILE))


def sha256(path: Path) -> str:
    """Hex SHA-256 of a file, read in 1 MiB blocks."""
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()
