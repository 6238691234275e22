"""KL autoencoder (the Stable Diffusion "VAE", small): 128x128x3 frames <-> 16x16x4 latents.

Trained on its own first (L1 reconstruction + a weak KL term, no GAN or perceptual
loss: the frames are clean simulator renders); the diffusion model then works in
its latent space, where a frame is 1,024 numbers.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from flax import nnx

from agnostos_mjx.dynamics.config import LATENT_CHANNELS, AutoencoderConfig
from agnostos_mjx.dynamics.layers import Downsample, GroupNorm, ResBlock, Upsample


def to_unit(frames: jax.Array) -> jax.Array:
    """uint8 [0, 255] -> float [-1, 1]."""
    return frames.astype(jnp.float32) / 127.5 - 1.0


def to_uint8(images: jax.Array) -> jax.Array:
    return jnp.clip(jnp.round((images + 1.0) * 127.5), 0, 255).astype(jnp.uint8)


class Encoder(nnx.Module):
    def __init__(self, cfg: AutoencoderConfig, *, rngs: nnx.Rngs):
        ch, g = cfg.channels, cfg.groups
        self.conv_in = nnx.Conv(3, ch[0], (3, 3), rngs=rngs)
        layers, cin = [], ch[0]
        for level, c in enumerate(ch):
            for _ in range(cfg.blocks):
                layers.append(ResBlock(cin, c, g, rngs=rngs))
                cin = c
            if level < len(ch) - 1:
                layers.append(Downsample(c, rngs=rngs))
        self.layers = nnx.List(layers)
        self.mid = ResBlock(cin, cin, g, rngs=rngs)
        self.norm = GroupNorm(cin, num_groups=g, rngs=rngs)
        self.conv_out = nnx.Conv(cin, 2 * LATENT_CHANNELS, (3, 3), rngs=rngs)

    def __call__(self, x: jax.Array) -> jax.Array:
        h = self.conv_in(x)
        for layer in self.layers:
            h = layer(h)
        h = self.mid(h)
        return self.conv_out(jax.nn.silu(self.norm(h)))


class Decoder(nnx.Module):
    def __init__(self, cfg: AutoencoderConfig, *, rngs: nnx.Rngs):
        ch, g = cfg.channels[::-1], cfg.groups
        self.conv_in = nnx.Conv(LATENT_CHANNELS, ch[0], (3, 3), rngs=rngs)
        self.mid = ResBlock(ch[0], ch[0], g, rngs=rngs)
        layers, cin = [], ch[0]
        for level, c in enumerate(ch):
            for _ in range(cfg.blocks):
                layers.append(ResBlock(cin, c, g, rngs=rngs))
                cin = c
            if level < len(ch) - 1:
                layers.append(Upsample(c, rngs=rngs))
        self.layers = nnx.List(layers)
        self.norm = GroupNorm(cin, num_groups=g, rngs=rngs)
        self.conv_out = nnx.Conv(cin, 3, (3, 3), rngs=rngs)

    def __call__(self, z: jax.Array) -> jax.Array:
        h = self.mid(self.conv_in(z))
        for layer in self.layers:
            h = layer(h)
        return self.conv_out(jax.nn.silu(self.norm(h)))


class Autoencoder(nnx.Module):
    """`decoder=False` builds the encoder alone: all that feature extraction needs
    (the shipped export, agnostos_mjx.dynamics.export, has no decoder weights)."""

    def __init__(self, cfg: AutoencoderConfig, *, decoder: bool = True, rngs: nnx.Rngs):
        self.encoder = Encoder(cfg, rngs=rngs)
        self.decoder = Decoder(cfg, rngs=rngs) if decoder else None

    def encode(self, frames: jax.Array) -> tuple[jax.Array, jax.Array]:
        """uint8 frames (B,128,128,3) -> mean and log-variance (B,16,16,4)."""
        moments = self.encoder(to_unit(frames))
        mean, logvar = jnp.split(moments, 2, axis=-1)
        return mean, jnp.clip(logvar, -30.0, 20.0)

    def decode(self, z: jax.Array) -> jax.Array:
        """Latents (B,16,16,4) -> images in [-1, 1]."""
        if self.decoder is None:
            raise ValueError("this autoencoder has no decoder (an export keeps the encoder only)")
        return self.decoder(z)


def autoencoder_loss(
    model: Autoencoder, frames: jax.Array, key: jax.Array, kl_weight: float
) -> jax.Array:
    """Per-pixel L1 of a reconstruction from a sampled latent + kl_weight x mean KL to N(0, 1)."""
    mean, logvar = model.encode(frames)
    z = mean + jnp.exp(0.5 * logvar) * jax.random.normal(key, mean.shape)
    recon = jnp.mean(jnp.abs(model.decode(z) - to_unit(frames)))
    kl = 0.5 * jnp.mean(mean**2 + jnp.exp(logvar) - 1.0 - logvar)
    return recon + kl_weight * kl
