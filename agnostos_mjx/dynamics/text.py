"""Instruction encoder: UTF-8 bytes + a small bidirectional transformer.

Bytes mean no vocabulary, so unseen tasks' words ("umbrella", "saucepan") still
get tokens.  Attention is bidirectional, so every token - the [CLS] included -
sees the whole prompt; the original took CLIP's causal BOS state, which is the
same for every prompt (xicm_reference.md, flaw 1).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
from flax import nnx

from agnostos_mjx.dynamics.config import FEATURE_DIM, TextConfig
from agnostos_mjx.dynamics.layers import MLP, attention

CLS, PAD = 256, 257
VOCAB = 258


def tokenize(texts: list[str], max_len: int) -> tuple[np.ndarray, np.ndarray]:
    """[CLS] + UTF-8 bytes, padded/cut to max_len -> ids (N, L) int32 and mask (N, L) bool.

    The empty string gives [CLS] alone: the "null prompt" of classifier-free guidance."""
    ids = np.full((len(texts), max_len), PAD, np.int32)
    for i, text in enumerate(texts):
        data = [CLS, *text.strip().lower().encode("utf-8")][:max_len]
        ids[i, : len(data)] = data
    return ids, ids != PAD


class Block(nnx.Module):
    def __init__(self, width: int, heads: int, *, rngs: nnx.Rngs):
        self.norm1 = nnx.LayerNorm(width, rngs=rngs)
        self.attn = attention(heads, width, rngs=rngs)
        self.norm2 = nnx.LayerNorm(width, rngs=rngs)
        self.mlp = MLP(width, rngs=rngs)

    def __call__(self, x: jax.Array, mask: jax.Array) -> jax.Array:
        x = x + self.attn(self.norm1(x), mask=mask[:, None, None, :])
        return x + self.mlp(self.norm2(x))


class TextEncoder(nnx.Module):
    """ids, mask -> per-token states (N, L, width) for cross-attention and a pooled
    1,024-d vector (masked mean, projected) that conditions the UNet globally and
    serves as the `lang` selection feature."""

    def __init__(self, cfg: TextConfig, *, rngs: nnx.Rngs):
        self.embed = nnx.Embed(VOCAB, cfg.width, rngs=rngs)
        self.pos = nnx.Param(0.02 * jax.random.normal(rngs.params(), (cfg.max_len, cfg.width)))
        self.blocks = nnx.List([Block(cfg.width, cfg.heads, rngs=rngs) for _ in range(cfg.depth)])
        self.norm = nnx.LayerNorm(cfg.width, rngs=rngs)
        self.pool = nnx.Linear(cfg.width, FEATURE_DIM, rngs=rngs)

    def __call__(self, ids: jax.Array, mask: jax.Array) -> tuple[jax.Array, jax.Array]:
        x = self.embed(ids) + self.pos[None, : ids.shape[1]]
        for block in self.blocks:
            x = block(x, mask)
        x = self.norm(x)
        m = mask[..., None].astype(x.dtype)
        pooled = (x * m).sum(1) / jnp.maximum(m.sum(1), 1.0)
        return x, self.pool(pooled)
