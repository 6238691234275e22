"""Building blocks shared by the autoencoder and the UNet (Stable Diffusion style, NHWC)."""

from __future__ import annotations

from collections.abc import Callable
from typing import TypeVar

import jax
import jax.numpy as jnp
from flax import nnx


class ResBlock(nnx.Module):
    """GroupNorm-SiLU-Conv twice, with an optional timestep/conditioning embedding added in between."""

    def __init__(
        self, cin: int, cout: int, groups: int, *, emb_dim: int | None = None, rngs: nnx.Rngs
    ):
        self.norm1 = nnx.GroupNorm(cin, num_groups=groups, rngs=rngs)
        self.conv1 = nnx.Conv(cin, cout, (3, 3), rngs=rngs)
        self.emb = nnx.Linear(emb_dim, cout, rngs=rngs) if emb_dim else None
        self.norm2 = nnx.GroupNorm(cout, num_groups=groups, rngs=rngs)
        # Zero-initialised last conv: each block starts as the identity, which keeps deep nets stable.
        self.conv2 = nnx.Conv(cout, cout, (3, 3), kernel_init=nnx.initializers.zeros, rngs=rngs)
        self.skip = nnx.Conv(cin, cout, (1, 1), rngs=rngs) if cin != cout else None

    def __call__(self, x: jax.Array, emb: jax.Array | None = None) -> jax.Array:
        h = self.conv1(jax.nn.silu(self.norm1(x)))
        if self.emb is not None:
            h = h + self.emb(jax.nn.silu(emb))[:, None, None, :]
        h = self.conv2(jax.nn.silu(self.norm2(h)))
        return h + (self.skip(x) if self.skip is not None else x)


class Downsample(nnx.Module):
    def __init__(self, c: int, *, rngs: nnx.Rngs):
        self.conv = nnx.Conv(c, c, (3, 3), strides=(2, 2), rngs=rngs)

    def __call__(self, x: jax.Array) -> jax.Array:
        return self.conv(x)


class Upsample(nnx.Module):
    """Nearest-neighbour x2 then a conv (no checkerboard artefacts of transposed convs)."""

    def __init__(self, c: int, *, rngs: nnx.Rngs):
        self.conv = nnx.Conv(c, c, (3, 3), rngs=rngs)

    def __call__(self, x: jax.Array) -> jax.Array:
        b, h, w, c = x.shape
        return self.conv(jax.image.resize(x, (b, 2 * h, 2 * w, c), "nearest"))


def attention(
    heads: int, width: int, *, kv_width: int | None = None, rngs: nnx.Rngs
) -> nnx.MultiHeadAttention:
    """Multi-head attention without dropout or stored RNG state (plain parameters only)."""
    return nnx.MultiHeadAttention(
        heads,
        width,
        in_kv_features=kv_width,
        decode=False,
        deterministic=True,
        keep_rngs=False,
        rngs=rngs,
    )


class MLP(nnx.Module):
    def __init__(self, width: int, *, mult: int = 4, rngs: nnx.Rngs):
        self.fc1 = nnx.Linear(width, mult * width, rngs=rngs)
        self.fc2 = nnx.Linear(mult * width, width, rngs=rngs)

    def __call__(self, x: jax.Array) -> jax.Array:
        return self.fc2(jax.nn.gelu(self.fc1(x)))


def sinusoidal(t: jax.Array, dim: int) -> jax.Array:
    """Transformer-style embedding of (possibly fractional) timesteps, (B,) -> (B, dim)."""
    half = dim // 2
    freqs = jnp.exp(-jnp.log(10_000.0) * jnp.arange(half) / half)
    args = t.astype(jnp.float32)[:, None] * freqs[None, :]
    return jnp.concatenate([jnp.sin(args), jnp.cos(args)], axis=-1)


M = TypeVar("M", bound=nnx.Module)


def create(build: Callable[[], M]) -> M:
    """Run a module constructor under one jit: one compile (cached on disk) instead
    of hundreds of small eager initialiser ops, which dominate start-up on CPU."""
    return nnx.jit(build)()


def abstract(build: Callable[[], M]) -> M:
    """The module's structure and shapes without computing any weights (to restore into)."""
    return nnx.eval_shape(build)
