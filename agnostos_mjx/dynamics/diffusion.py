"""The dynamics diffusion model: predict a demo's last-frame latent from its first
frame and instruction (InstructPix2Pix-style), trained with classifier-free
conditioning dropout and sampled with DDIM and two guidance scales.
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np
from flax import nnx

from agnostos_mjx.dynamics.config import DiffusionConfig, TextConfig, UNetConfig
from agnostos_mjx.dynamics.text import TextEncoder, tokenize
from agnostos_mjx.dynamics.unet import UNet


def alphas_cumprod(cfg: DiffusionConfig) -> np.ndarray:
    """alpha_bar_t for t = 0..T-1 ("cosine": Nichol & Dhariwal 2021; "scaled_linear": Stable Diffusion)."""
    T = cfg.timesteps
    if cfg.schedule == "cosine":
        s = 0.008
        f = np.cos((np.arange(T + 1) / T + s) / (1 + s) * math.pi / 2) ** 2
        betas = np.clip(1.0 - f[1:] / f[:-1], 0.0, 0.999)
    elif cfg.schedule == "scaled_linear":
        betas = np.linspace(0.00085**0.5, 0.012**0.5, T) ** 2
    else:
        raise ValueError(f"unknown schedule {cfg.schedule!r} (cosine or scaled_linear)")
    return np.cumprod(1.0 - betas).astype(np.float32)


class DynamicsModel(nnx.Module):
    """Text encoder + UNet; one call = one denoiser evaluation."""

    def __init__(self, text: TextConfig, unet: UNetConfig, *, rngs: nnx.Rngs):
        self.text = TextEncoder(text, rngs=rngs)
        self.unet = UNet(unet, text.width, rngs=rngs)

    def __call__(
        self, x_t: jax.Array, t: jax.Array, cond: jax.Array, ids: jax.Array, mask: jax.Array
    ) -> jax.Array:
        ctx, pooled = self.text(ids, mask)
        return self.unet(x_t, cond, t, ctx, mask, pooled)


def _split(
    out: jax.Array, x_t: jax.Array, ab: jax.Array, prediction: str
) -> tuple[jax.Array, jax.Array]:
    """Model output -> (x0, epsilon) estimates; ab = alpha_bar_t broadcastable to x_t."""
    sa, sb = jnp.sqrt(ab), jnp.sqrt(1.0 - ab)
    if prediction == "v":
        return sa * x_t - sb * out, sb * x_t + sa * out
    if prediction == "epsilon":
        # At the cosine schedule's last step sqrt(alpha_bar) ~ 0; epsilon is best
        # paired with scaled_linear, the clamp only keeps the other pairing finite.
        return (x_t - sb * out) / jnp.maximum(sa, 1e-3), out
    raise ValueError(f"unknown prediction {prediction!r} (v or epsilon)")


def diffusion_loss(
    model: DynamicsModel,
    cfg: DiffusionConfig,
    z_first: jax.Array,
    z_last: jax.Array,
    ids: jax.Array,
    mask: jax.Array,
    key: jax.Array,
) -> jax.Array:
    """MSE on epsilon or v at a uniform random timestep.  Conditioning dropout
    (InstructPix2Pix): instruction alone, first frame alone, or both are replaced
    by the null prompt / a zero latent, so one network learns all the
    (un)conditional scores that two-scale guidance needs at sampling."""
    b = z_first.shape[0]
    k_t, k_n, k_d = jax.random.split(key, 3)
    ab_all = jnp.asarray(alphas_cumprod(cfg))
    t = jax.random.randint(k_t, (b,), 0, cfg.timesteps)
    ab = ab_all[t][:, None, None, None]
    noise = jax.random.normal(k_n, z_last.shape)
    x_t = jnp.sqrt(ab) * z_last + jnp.sqrt(1.0 - ab) * noise
    target = (
        noise if cfg.prediction == "epsilon" else jnp.sqrt(ab) * noise - jnp.sqrt(1.0 - ab) * z_last
    )

    u = jax.random.uniform(k_d, (b,))
    p1, p2, p3 = (
        cfg.drop_text,
        cfg.drop_text + cfg.drop_image,
        cfg.drop_text + cfg.drop_image + cfg.drop_both,
    )
    drop_text = (u < p1) | ((u >= p2) & (u < p3))
    drop_image = (u >= p1) & (u < p3)
    null_ids, null_mask = (jnp.asarray(a) for a in tokenize([""], ids.shape[1]))
    ids = jnp.where(drop_text[:, None], null_ids, ids)
    mask = jnp.where(drop_text[:, None], null_mask, mask)
    cond = jnp.where(drop_image[:, None, None, None], 0.0, z_first)

    out = model(x_t, t, cond, ids, mask)
    return jnp.mean((out - target) ** 2)


def ddim_sample(
    model: DynamicsModel,
    cfg: DiffusionConfig,
    z_first: jax.Array,
    ids: jax.Array,
    mask: jax.Array,
    noise: jax.Array,
) -> jax.Array:
    """Deterministic DDIM (eta = 0) from `noise` to a last-frame latent, with
    InstructPix2Pix guidance: out = u + s_I (o_I - u) + s_T (o_IT - o_I), where
    u = no conditioning, o_I = first frame only, o_IT = both.  The three
    evaluations run as one batch of 3B."""
    b, L = z_first.shape[0], ids.shape[1]
    ab_all = jnp.asarray(alphas_cumprod(cfg))
    ts = np.linspace(cfg.timesteps - 1, 0, cfg.sample_steps).round().astype(np.int32)
    prev = np.append(ts[1:], -1)

    null_ids, null_mask = (jnp.broadcast_to(jnp.asarray(a), (b, L)) for a in tokenize([""], L))
    ids3 = jnp.concatenate([ids, null_ids, null_ids])
    mask3 = jnp.concatenate([mask, null_mask, null_mask])
    cond3 = jnp.concatenate([z_first, z_first, jnp.zeros_like(z_first)])
    ctx, pooled = model.text(ids3, mask3)  # the text does not change over steps: encode once

    def step(x: jax.Array, tp: tuple[jax.Array, jax.Array]) -> tuple[jax.Array, None]:
        t, t_prev = tp
        ab = ab_all[t]
        ab_prev = jnp.where(t_prev >= 0, ab_all[jnp.maximum(t_prev, 0)], 1.0)
        x3 = jnp.concatenate([x, x, x])
        out = model.unet(x3, cond3, jnp.full((3 * b,), t), ctx, mask3, pooled)
        o_it, o_i, o_u = jnp.split(out, 3)
        guided = o_u + cfg.image_guidance * (o_i - o_u) + cfg.text_guidance * (o_it - o_i)
        x0, eps = _split(guided, x, ab, cfg.prediction)
        return jnp.sqrt(ab_prev) * x0 + jnp.sqrt(1.0 - ab_prev) * eps, None

    x, _ = jax.lax.scan(step, noise, (jnp.asarray(ts), jnp.asarray(prev)))
    return x
