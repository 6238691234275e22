"""A trained autoencoder + dynamics model, loaded from their run directories or
from an export, with the batched inference calls the features and the evaluation need."""

from __future__ import annotations

import functools
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from flax import nnx

from agnostos_mjx.dynamics.autoencoder import Autoencoder, to_uint8
from agnostos_mjx.dynamics.batching import map_chunks
from agnostos_mjx.dynamics.checkpoint import CheckpointError, load_params, read_meta
from agnostos_mjx.dynamics.config import (
    LATENT_CHANNELS,
    LATENT_SIZE,
    AutoencoderConfig,
    DiffusionConfig,
    TextConfig,
    UNetConfig,
    from_dict,
    to_dict,
)
from agnostos_mjx.dynamics.diffusion import DynamicsModel, ddim_sample
from agnostos_mjx.dynamics.export_format import is_export, read_models
from agnostos_mjx.dynamics.layers import abstract
from agnostos_mjx.dynamics.text import tokenize

AE_KIND, DYN_KIND = "autoencoder", "dynamics"
_MODEL_FIELDS = ("prediction", "schedule", "timesteps")  # diffusion fields fixed at training


def autoencoder_meta(cfg: AutoencoderConfig) -> dict[str, Any]:
    return {"kind": AE_KIND, "model": {"autoencoder": to_dict(cfg)}}


def dynamics_meta(
    text: TextConfig, unet: UNetConfig, diffusion: DiffusionConfig, ae: AutoencoderConfig
) -> dict[str, Any]:
    d = to_dict(diffusion)
    return {
        "kind": DYN_KIND,
        "diffusion": to_dict(diffusion),  # sampling defaults for Pipeline.load
        "model": {
            "text": to_dict(text),
            "unet": to_dict(unet),
            "autoencoder": to_dict(ae),
            **{k: d[k] for k in _MODEL_FIELDS},
        },
    }


def load_autoencoder(run: str | Path) -> tuple[Autoencoder, AutoencoderConfig]:
    """The autoencoder of a run directory, built from the config in its checkpoint."""
    meta = _meta(run, AE_KIND)
    cfg = from_dict(AutoencoderConfig, meta["model"]["autoencoder"])
    model = abstract(lambda: Autoencoder(cfg, rngs=nnx.Rngs(0)))
    return load_params(run, model, {"kind": AE_KIND, "model": meta["model"]}), cfg


def _meta(run: str | Path, kind: str) -> dict[str, Any]:
    meta = read_meta(run)
    if meta.get("kind") != kind:
        raise CheckpointError(f"{run} holds a {meta.get('kind')!r} checkpoint, expected {kind!r}")
    return meta


# Pure jitted functions of a module's (graph, state) split: several threads may call them at
# once (the selection's workers).  nnx.jit updates the module object it is given on every
# call, which two threads calling with one module break.
@functools.partial(jax.jit, static_argnums=0)
def _encode(graph: nnx.GraphDef, state: nnx.State, frames: jax.Array) -> jax.Array:
    ae = nnx.merge(graph, state)
    return ae.encode(frames)[0]  # the mode of q(z|x), as the original's latent_dist.mode()


@functools.partial(jax.jit, static_argnums=0)
def _decode(graph: nnx.GraphDef, state: nnx.State, z: jax.Array) -> jax.Array:
    return to_uint8(nnx.merge(graph, state).decode(z))


@functools.partial(jax.jit, static_argnums=(0, 2))
def _sample(graph: nnx.GraphDef, state: nnx.State, cfg: DiffusionConfig, z_first: jax.Array,
            ids: jax.Array, mask: jax.Array) -> jax.Array:
    # The same initial noise for every query: features do not depend on batch order or size.
    noise = jax.random.normal(
        jax.random.key(cfg.sample_seed), (LATENT_SIZE, LATENT_SIZE, LATENT_CHANNELS)
    )
    model = nnx.merge(graph, state)
    return ddim_sample(model, cfg, z_first, ids, mask, jnp.broadcast_to(noise, z_first.shape))


def first_and_predicted_latents(ae_graph: nnx.GraphDef, ae_state: nnx.State,
                                graph: nnx.GraphDef, state: nnx.State, cfg: DiffusionConfig,
                                latent_scale: float, frames: jax.Array, ids: jax.Array,
                                mask: jax.Array, predict: bool = True
                                ) -> tuple[jax.Array, jax.Array | None]:
    """Traceable `Pipeline.encode` then `Pipeline.predict` (None without `predict`), for
    programs that go on from the latents (the selection's one program per query chunk)."""
    z = _encode(ae_graph, ae_state, frames) * latent_scale
    return z, (_sample(graph, state, cfg, z, ids, mask) if predict else None)


@functools.partial(jax.jit, static_argnums=0)
def _pooled(graph: nnx.GraphDef, state: nnx.State, ids: jax.Array, mask: jax.Array
            ) -> jax.Array:
    return nnx.merge(graph, state).text(ids, mask)[1]


# Rows per compiled call (batching.py pads every call to it).  An accelerator's call costs
# less per row in larger chunks, so it takes a large one.  On the CPU the cost per query
# barely falls beyond chunks of 4, and 4 wastes least on the evaluation's small rounds (1-3
# replanning worlds are common late in a task); chunks of 64 ran slower per row there, the
# weights no longer fitting the caches (docs/performance.md).
ACCELERATOR_CHUNK, CPU_CHUNK = 64, 4


def default_chunk() -> int:
    return CPU_CHUNK if jax.default_backend() == "cpu" else ACCELERATOR_CHUNK


@dataclass
class Pipeline:
    """Latents are in the diffusion model's units: autoencoder mean x latent_scale.
    `chunk`: rows per compiled call, None for `default_chunk()` (by backend)."""

    ae: Autoencoder
    latent_scale: float
    model: DynamicsModel | None = None
    text: TextConfig | None = None
    diffusion: DiffusionConfig = DiffusionConfig()
    chunk: int | None = None
    identity: str = ""  # run path, step and sampling settings: keys cached feature indices

    @classmethod
    def load(
        cls,
        run: str | Path,
        ae_run: str | Path | None = None,
        chunk: int | None = None,
        **sampling: Any,
    ) -> Pipeline:
        """Load a dynamics run (and the autoencoder it was trained on, or `ae_run`), or an
        export directory (python -m agnostos_mjx.train.export: float16 weights cast back to
        float32, no decoder).  `sampling` overrides sampling fields: sample_steps,
        image_guidance, text_guidance, sample_seed."""
        if not Path(run).is_dir():
            raise CheckpointError(
                f"no dynamics model at {Path(run).absolute()}: expected an export "
                "(export.json + params.npz) or a training run directory (checkpoints/)"
            )
        if is_export(run):
            if ae_run is not None:
                raise CheckpointError(f"{run} is an export: it holds its own encoder, drop ae_run")
            return cls.from_export(run, chunk, **sampling)
        meta = _meta(run, DYN_KIND)
        m = meta["model"]
        text, unet = from_dict(TextConfig, m["text"]), from_dict(UNetConfig, m["unet"])
        diffusion = replace(from_dict(DiffusionConfig, meta["diffusion"]), **sampling)
        ae_run = ae_run or meta["autoencoder_dir"]
        ae, ae_cfg = load_autoencoder(ae_run)
        if to_dict(ae_cfg) != m["autoencoder"]:
            raise CheckpointError(
                f"autoencoder at {ae_run} has another config than the one {run} was trained on"
            )
        model = abstract(lambda: DynamicsModel(text, unet, rngs=nnx.Rngs(0)))
        model = load_params(run, model, {"kind": DYN_KIND, "model": m})
        identity = f"{Path(run).absolute()}@{meta['step']}|{to_dict(diffusion)}"
        return cls(ae, meta["latent_scale"], model, text, diffusion, chunk, identity)

    @classmethod
    def from_export(cls, path: str | Path, chunk: int | None = None, **sampling: Any) -> Pipeline:
        """A feature-extraction pipeline from an export directory (float32 weights, no
        decoder); CheckpointError naming the path if the export is damaged."""
        ae, scale, model, text, diffusion, identity = read_models(path, **sampling)
        return cls(ae, scale, model, text, diffusion, chunk, identity)

    @property
    def chunk_size(self) -> int:
        return self.chunk or default_chunk()

    @functools.cached_property
    def ae_split(self) -> tuple[nnx.GraphDef, nnx.State]:
        return nnx.split(self.ae)

    @functools.cached_property
    def model_split(self) -> tuple[nnx.GraphDef, nnx.State]:
        return nnx.split(self.model)

    def encode(self, frames: np.ndarray) -> np.ndarray:
        """uint8 (N,128,128,3) -> scaled latents (N,16,16,4)."""
        latents = map_chunks(lambda f: _encode(*self.ae_split, f), frames, size=self.chunk_size)
        return latents * self.latent_scale

    def decode(self, latents: np.ndarray) -> np.ndarray:
        """Scaled latents -> uint8 frames."""
        latents = np.asarray(latents) / self.latent_scale
        return map_chunks(lambda z: _decode(*self.ae_split, z), latents, size=self.chunk_size)

    def tokens(self, instructions: list[str]) -> tuple[np.ndarray, np.ndarray]:
        return tokenize(instructions, self.text.max_len)

    def predict(self, first_latents: np.ndarray, instructions: list[str]) -> np.ndarray:
        """Predicted last-frame latents (N,16,16,4) by guided DDIM from fixed noise."""
        ids, mask = self.tokens(instructions)
        graph, state = self.model_split
        fn = lambda z, i, m: _sample(graph, state, self.diffusion, z, i, m)
        z = np.asarray(first_latents, np.float32)
        return map_chunks(fn, z, ids, mask, size=self.chunk_size)

    def lang(self, instructions: list[str]) -> np.ndarray:
        """Pooled, projected instruction features (N, 1024)."""
        ids, mask = self.tokens(instructions)
        fn = lambda i, m: _pooled(*self.model_split, i, m)
        return map_chunks(fn, ids, mask, size=self.chunk_size)
