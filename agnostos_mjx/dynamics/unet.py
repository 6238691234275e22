"""The denoiser: a small Stable-Diffusion-style UNet over 16x16 latents.

InstructPix2Pix conditioning: the first-frame latent is concatenated to the noisy
last-frame latent (8 input channels); the instruction enters through
cross-attention to its token states and, pooled, through the timestep embedding.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from flax import nnx

from agnostos_mjx.dynamics.config import FEATURE_DIM, LATENT_CHANNELS, UNetConfig
from agnostos_mjx.dynamics.layers import (
    MLP,
    Downsample,
    GroupNorm,
    ResBlock,
    Upsample,
    attention,
    sinusoidal,
)


class Transformer(nnx.Module):
    """Self-attention over latent pixels, cross-attention to text tokens, MLP."""

    def __init__(self, c: int, ctx_width: int, heads: int, groups: int, *, rngs: nnx.Rngs):
        self.norm = GroupNorm(c, num_groups=groups, rngs=rngs)
        self.norm1, self.self_attn = nnx.LayerNorm(c, rngs=rngs), attention(heads, c, rngs=rngs)
        self.norm2 = nnx.LayerNorm(c, rngs=rngs)
        self.cross_attn = attention(heads, c, kv_width=ctx_width, rngs=rngs)
        self.norm3, self.mlp = nnx.LayerNorm(c, rngs=rngs), MLP(c, rngs=rngs)
        self.proj_out = nnx.Linear(c, c, kernel_init=nnx.initializers.zeros, rngs=rngs)

    def __call__(self, x: jax.Array, ctx: jax.Array, ctx_mask: jax.Array) -> jax.Array:
        b, h, w, c = x.shape
        t = self.norm(x).reshape(b, h * w, c)
        t = t + self.self_attn(self.norm1(t))
        t = t + self.cross_attn(self.norm2(t), ctx, mask=ctx_mask[:, None, None, :])
        t = t + self.mlp(self.norm3(t))
        return x + self.proj_out(t).reshape(b, h, w, c)


class Stage(nnx.Module):
    """One ResBlock, optionally followed by a Transformer."""

    def __init__(
        self,
        cin: int,
        cout: int,
        emb: int,
        ctx: int,
        attn: bool,
        cfg: UNetConfig,
        *,
        rngs: nnx.Rngs,
    ):
        self.res = ResBlock(cin, cout, cfg.groups, emb_dim=emb, rngs=rngs)
        self.attn = Transformer(cout, ctx, cfg.heads, cfg.groups, rngs=rngs) if attn else None

    def __call__(
        self, x: jax.Array, emb: jax.Array, ctx: jax.Array, ctx_mask: jax.Array
    ) -> jax.Array:
        x = self.res(x, emb)
        return self.attn(x, ctx, ctx_mask) if self.attn is not None else x


class UNet(nnx.Module):
    def __init__(self, cfg: UNetConfig, ctx_width: int, *, rngs: nnx.Rngs):
        ch, c0 = cfg.channels, cfg.channels[0]
        emb = 4 * c0
        self.time1, self.time2 = nnx.Linear(c0, emb, rngs=rngs), nnx.Linear(emb, emb, rngs=rngs)
        self.text_emb = nnx.Linear(FEATURE_DIM, emb, rngs=rngs)
        self.conv_in = nnx.Conv(2 * LATENT_CHANNELS, c0, (3, 3), rngs=rngs)

        down, skips, cin = [], [c0], c0
        for level, c in enumerate(ch):
            for _ in range(cfg.blocks):
                down.append(Stage(cin, c, emb, ctx_width, cfg.attention[level], cfg, rngs=rngs))
                cin = c
                skips.append(c)
            if level < len(ch) - 1:
                down.append(Downsample(c, rngs=rngs))
                skips.append(c)
        self.down = nnx.List(down)
        self.mid1 = Stage(cin, cin, emb, ctx_width, True, cfg, rngs=rngs)
        self.mid2 = ResBlock(cin, cin, cfg.groups, emb_dim=emb, rngs=rngs)

        up = []
        for level in reversed(range(len(ch))):
            for _ in range(cfg.blocks + 1):
                up.append(
                    Stage(
                        cin + skips.pop(),
                        ch[level],
                        emb,
                        ctx_width,
                        cfg.attention[level],
                        cfg,
                        rngs=rngs,
                    )
                )
                cin = ch[level]
            if level > 0:
                up.append(Upsample(cin, rngs=rngs))
        self.up = nnx.List(up)
        self.norm_out = GroupNorm(cin, num_groups=cfg.groups, rngs=rngs)
        self.conv_out = nnx.Conv(
            cin, LATENT_CHANNELS, (3, 3), kernel_init=nnx.initializers.zeros, rngs=rngs
        )
        self.c0 = c0

    def __call__(
        self,
        x_t: jax.Array,
        cond: jax.Array,
        t: jax.Array,
        ctx: jax.Array,
        ctx_mask: jax.Array,
        pooled: jax.Array,
    ) -> jax.Array:
        """x_t, cond: (B,16,16,4); t: (B,) timesteps; ctx: (B,L,D) text tokens; pooled: (B,1024)."""
        emb = self.time2(jax.nn.silu(self.time1(sinusoidal(t, self.c0)))) + self.text_emb(pooled)
        h = self.conv_in(jnp.concatenate([x_t, cond], axis=-1))
        skips = [h]
        for layer in self.down:
            h = layer(h, emb, ctx, ctx_mask) if isinstance(layer, Stage) else layer(h)
            skips.append(h)
        h = self.mid2(self.mid1(h, emb, ctx, ctx_mask), emb)
        for layer in self.up:
            if isinstance(layer, Stage):
                h = layer(jnp.concatenate([h, skips.pop()], axis=-1), emb, ctx, ctx_mask)
            else:
                h = layer(h)
        return self.conv_out(jax.nn.silu(self.norm_out(h)))
