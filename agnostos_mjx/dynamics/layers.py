"""Building blocks shared by the autoencoder and the UNet (Stable Diffusion style, NHWC)."""

from __future__ import annotations

import contextlib
from collections.abc import Callable, Iterator
from typing import TypeVar

import jax
import jax.numpy as jnp
from flax import nnx


class GroupNorm(nnx.GroupNorm):
    """`nnx.GroupNorm` (same parameters, statistics and formula: E[x^2] - E[x]^2, the same
    values up to float round-off) with the statistics summed per channel over the spatial
    axes first, then per group.  flax reduces a (..., groups, size) view over non-adjacent
    axes, which XLA's CPU backend ran several times slower at the UNet's shapes (issue 13;
    docs/performance.md).  Options other than the models' (masks, dtypes, ...) take flax's path."""

    def __call__(self, x: jax.Array, *, mask: jax.Array | None = None) -> jax.Array:
        if (mask is not None or self.reduction_axes is not None or self.axis_name is not None
                or not self.use_fast_variance or self.scale is None or self.bias is None
                or self.dtype is not None or x.dtype != jnp.float32 or x.ndim < 3
                or self.scale[...].dtype != jnp.float32):
            return super().__call__(x, mask=mask)  # the general case, as flax computes it
        b, c = x.shape[0], x.shape[-1]
        flat = x.reshape(b, -1, c)
        n = flat.shape[1] * self.group_size
        mean = flat.sum(1).reshape(b, self.num_groups, -1).sum(-1) / n  # (b, groups)
        mean2 = (flat * flat).sum(1).reshape(b, self.num_groups, -1).sum(-1) / n
        var = jnp.maximum(0.0, mean2 - mean * mean)
        mul = jnp.repeat(jax.lax.rsqrt(var + self.epsilon), self.group_size, axis=1)
        mul = mul * self.scale[...]
        mean = jnp.repeat(mean, self.group_size, axis=1)
        shape = (b,) + (1,) * (x.ndim - 2) + (c,)
        return (x - mean.reshape(shape)) * mul.reshape(shape) + self.bias[...]


class ResBlock(nnx.Module):
    """GroupNorm-SiLU-Conv twice, with an optional timestep/conditioning embedding added in between."""

    def __init__(
        self, cin: int, cout: int, groups: int, *, emb_dim: int | None = None, rngs: nnx.Rngs
    ):
        self.norm1 = GroupNorm(cin, num_groups=groups, rngs=rngs)
        self.conv1 = nnx.Conv(cin, cout, (3, 3), rngs=rngs)
        self.emb = nnx.Linear(emb_dim, cout, rngs=rngs) if emb_dim else None
        self.norm2 = GroupNorm(cout, num_groups=groups, rngs=rngs)
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


def dot_product_attention(
    query: jax.Array,
    key: jax.Array,
    value: jax.Array,
    mask: jax.Array | None = None,
    *,
    dropout_rate: float = 0.0,
    is_causal: bool = False,
    precision: jax.lax.PrecisionLike = None,
    **_: object,
) -> jax.Array:
    """flax's `nnx.dot_product_attention` (the same scaling, masking and softmax: the same
    values up to float round-off), arranged for XLA's CPU backend, several times faster on the
    UNet's 16x16 self-attention (256 tokens, 4 heads of 16; docs/performance.md):

    * the heads are moved ahead of the sequence axes before both matmuls: flax contracts
      `...qhd,...khd` and `...hqk,...khd` directly, which runs as strided batched matmuls;
    * the softmax is normalised after the weighted sum of the values (exp(w - max) @ v /
      sum(exp(w - max))): one division per output instead of per attention weight.

    No dropout or bias: the models here use neither."""
    if dropout_rate or is_causal:
        raise ValueError("dot_product_attention here has no dropout and no causal mask")
    query = query / jnp.sqrt(query.shape[-1]).astype(query.dtype)
    q, k, v = (x.swapaxes(-3, -2) for x in (query, key, value))  # (..., heads, seq, depth)
    weights = jnp.einsum("...hqd,...hkd->...hqk", q, k, precision=precision)
    if mask is not None:
        weights = jnp.where(mask, weights, jnp.finfo(weights.dtype).min)
    weights = jnp.exp(weights - jax.lax.stop_gradient(weights.max(-1, keepdims=True)))
    out = jnp.einsum("...hqk,...hkd->...hqd", weights, v, precision=precision)
    return (out / weights.sum(-1, keepdims=True)).swapaxes(-3, -2)


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
        attention_fn=dot_product_attention,
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


@contextlib.contextmanager
def cheap_tracer_attribute_errors() -> Iterator[None]:
    """Trace module constructors without a quadratic cost that would never be seen.

    Each RNG draw in a flax constructor updates the Rngs counter, and flax's
    ``Variable.set_value`` then probes ``getattr(value, "sharding", None)``.  On a tracer,
    JAX answers with an AttributeError whose message it builds first by walking back
    through every equation traced so far (``_origin_msg``); ``getattr`` swallows the
    message.  Over the dynamics model's ~1,600 draws that walk was most of building its
    abstract model with jax 0.10 (every process loading the shipped model paid it;
    docs/performance.md).  Here the message is left empty
    while a constructor is traced; where JAX lacks that method, nothing changes."""
    try:
        from jax._src.interpreters import partial_eval
        tracer = partial_eval.DynamicJaxprTracer
        original = tracer.__dict__["_origin_msg"]
    except (ImportError, AttributeError, KeyError):
        yield
        return
    tracer._origin_msg = lambda self: ""
    try:
        yield
    finally:
        tracer._origin_msg = original


def create(build: Callable[[], M]) -> M:
    """Run a module constructor under one jit: one compile (cached on disk) instead
    of hundreds of small eager initialiser ops, which dominate start-up on CPU."""
    with cheap_tracer_attribute_errors():
        return nnx.jit(build)()


def abstract(build: Callable[[], M]) -> M:
    """The module's structure and shapes without computing any weights (to restore into)."""
    with cheap_tracer_attribute_errors():
        return nnx.eval_shape(build)
