"""The reference VLA's network: a small RVT-style keyframe policy in Flax NNX.

Input: the three virtual views of the fused point cloud (views.py), the instruction as
UTF-8 bytes (the dynamics model's byte-level text encoder, trained from scratch here: no
vocabulary, so an unseen task's words still get tokens, but their meaning comes only from
the 18 seen tasks' instructions) and the proprioception (gripper open, the key-action
index).  The views are cut into patches; patches of all views, the text tokens and one
proprioception token go through one transformer.  Output: per view a heatmap over its
pixels (the next key action's position: views.decode_position), and from the tokens
pooled under those heatmaps and over everything, X-ICM's 72 Euler bins per axis
(textualise.quat_to_euler_bins) and the gripper's open amount (11 bins: 0, 0.1, ..., 1).
"""

from __future__ import annotations

from dataclasses import dataclass

import jax
import jax.numpy as jnp
from flax import nnx

from agnostos_mjx.dynamics.config import (
    TextConfig,
    _f,  # a field with its --flag help
)
from agnostos_mjx.dynamics.text import Block, TextEncoder
from agnostos_mjx.vla.views import CHANNELS, VIEWS, decode_position, target_heatmaps

ROT_BINS = 72  # X-ICM's 5-degree Euler bins (textualise.quat_to_euler_bins)
# The gripper's open amount in steps of 0.1: the experts use 1 (open), 0 (grasp) and
# in-between amounts to push (push_buttons 0.1, slide_block_to_color_target 0.5), which an
# open/close flag would lose.
GRIP_BINS = 11
MAX_STEPS = 25  # key-action index embedding (tasks.base.MAX_KEY_ACTIONS)


@dataclass(frozen=True)
class VLAConfig:
    """Sizes of the reference VLA (every field is a --vla-<field> flag)."""

    view_size: int = _f(96, "pixels per side of each virtual view (the cube is 1 m)")
    patch: int = _f(6, "patch side in view pixels (tokens per view: (view_size / patch)^2)")
    width: int = _f(256, "transformer width")
    depth: int = _f(6, "transformer layers")
    heads: int = _f(8, "attention heads")
    text_width: int = _f(128, "byte text encoder width")
    text_depth: int = _f(2, "byte text encoder layers")
    text_len: int = _f(96, "instruction bytes incl. [CLS] (longer ones are cut)")
    sigma: float = _f(1.5, "std (view pixels) of the Gaussian heatmap targets")
    rot_weight: float = _f(1.0, "weight of the rotation loss (3 axes, cross-entropy)")
    grip_weight: float = _f(1.0, "weight of the gripper loss")

    def __post_init__(self) -> None:
        if self.view_size % self.patch:
            raise ValueError(f"view_size {self.view_size} is not a multiple of patch {self.patch}")
        if self.width % self.heads:
            raise ValueError(f"width {self.width} is not a multiple of heads {self.heads}")

    @property
    def text(self) -> TextConfig:
        return TextConfig(width=self.text_width, depth=self.text_depth,
                          heads=max(1, self.text_width // 64), max_len=self.text_len)


VLA_DEFAULT = VLAConfig()
VLA_QUICK = VLAConfig(view_size=16, patch=4, width=32, depth=1, heads=2, text_width=32,
                      text_depth=1, text_len=64)


class ReferenceVLA(nnx.Module):
    """views (B, 3, S, S, C), text ids/mask (B, L), gripper_open (B,), step (B,) ->
    heatmap logits (B, 3, S, S), rotation logits (B, 3, 72), gripper logits (B, 11)."""

    def __init__(self, cfg: VLAConfig, *, rngs: nnx.Rngs):
        self.cfg = cfg
        s, p, d = cfg.view_size, cfg.patch, cfg.width
        self.grid = s // p
        self.stem = nnx.Conv(CHANNELS, 32, (3, 3), rngs=rngs)
        self.patchify = nnx.Linear(p * p * 32, d, rngs=rngs)
        n = len(VIEWS) * self.grid**2
        self.pos = nnx.Param(0.02 * jax.random.normal(rngs.params(), (n, d)))
        self.text = TextEncoder(cfg.text, rngs=rngs)
        self.text_proj = nnx.Linear(cfg.text_width, d, rngs=rngs)
        self.step_embed = nnx.Embed(MAX_STEPS, d, rngs=rngs)
        self.grip_embed = nnx.Linear(1, d, rngs=rngs)
        self.blocks = nnx.List([Block(d, cfg.heads, rngs=rngs) for _ in range(cfg.depth)])
        self.norm = nnx.LayerNorm(d, rngs=rngs)
        # Heatmap head: per token p*p*16 features -> pixels, then a conv with the stem's.
        self.up = nnx.Linear(d, p * p * 16, rngs=rngs)
        self.refine1 = nnx.Conv(16 + 32, 32, (3, 3), rngs=rngs)
        self.refine2 = nnx.Conv(32, 1, (3, 3), rngs=rngs)
        self.head = nnx.Sequential(nnx.Linear(4 * d, 2 * d, rngs=rngs), nnx.gelu,
                                   nnx.Linear(2 * d, 3 * ROT_BINS + GRIP_BINS, rngs=rngs))

    def __call__(self, views: jax.Array, ids: jax.Array, mask: jax.Array,
                 gripper_open: jax.Array, step: jax.Array,
                 pool: jax.Array | None = None) -> tuple[jax.Array, ...]:
        """`pool` (B, 3, S, S): where to pool the tokens for rotation and gripper; default
        the predicted heatmaps (training passes the targets, as RVT-2 does, so that those
        heads see the right place from the first step)."""
        b, v, s, _, _ = views.shape
        p, g = self.cfg.patch, self.grid
        stem = nnx.gelu(self.stem(views.reshape(b * v, s, s, CHANNELS)))  # (BV, S, S, 32)
        patches = stem.reshape(b * v, g, p, g, p, 32).transpose(0, 1, 3, 2, 4, 5)
        tokens = self.patchify(patches.reshape(b, v * g * g, p * p * 32)) + self.pos[None]
        text, _ = self.text(ids, mask)
        proprio = (self.step_embed(jnp.clip(step, 0, MAX_STEPS - 1))
                   + self.grip_embed(gripper_open[:, None].astype(jnp.float32)))
        x = jnp.concatenate([tokens, self.text_proj(text), proprio[:, None]], 1)
        full = jnp.concatenate([jnp.ones((b, tokens.shape[1]), bool), mask,
                                jnp.ones((b, 1), bool)], 1)
        for block in self.blocks:
            x = block(x, full)
        x = self.norm(x)
        vis = x[:, : tokens.shape[1]].reshape(b, v, g, g, -1)
        # Heatmaps: tokens -> p x p pixels each, refined with the stem's features.
        up = self.up(vis).reshape(b * v, g, g, p, p, 16).transpose(0, 1, 3, 2, 4, 5)
        up = up.reshape(b * v, s, s, 16)
        h = nnx.gelu(self.refine1(jnp.concatenate([up, stem], -1)))
        logits = self.refine2(h).reshape(b, v, s, s)
        # Rotation and gripper from the tokens pooled under each view's heatmap (no
        # gradient through the weights) and the proprioception token (it attends to all).
        if pool is None:
            pool = jax.nn.softmax(logits.reshape(b, v, -1), -1)
        prob = jax.lax.stop_gradient(pool).reshape(b, v, g, p, g, p).sum((3, 5))  # (B,V,g,g)
        local = jnp.einsum("bvij,bvijd->bvd", prob, vis).reshape(b, -1)  # (B, 3D)
        out = self.head(jnp.concatenate([local, x[:, -1]], -1))
        rot = out[:, : 3 * ROT_BINS].reshape(b, 3, ROT_BINS)
        return logits, rot, out[:, 3 * ROT_BINS:]


def vla_loss(model: ReferenceVLA, batch: dict[str, jax.Array]) -> tuple[jax.Array, dict]:
    """Heatmap cross-entropy (3 views, Gaussian targets) + rotation bins + gripper."""
    cfg = model.cfg
    target = target_heatmaps(batch["target_pos"], cfg.view_size, cfg.sigma)
    logits, rot, grip = model(batch["views"], batch["ids"], batch["mask"],
                              batch["gripper_open"], batch["step"], pool=target)
    b = logits.shape[0]
    logp = jax.nn.log_softmax(logits.reshape(b, 3, -1), -1)
    pos_loss = -(target.reshape(b, 3, -1) * logp).sum(-1).sum(-1).mean()
    rot_loss = -jnp.take_along_axis(jax.nn.log_softmax(rot, -1),
                                    batch["target_rot"][..., None], -1).sum((1, 2)).mean()
    grip_loss = -jnp.take_along_axis(jax.nn.log_softmax(grip, -1),
                                     batch["target_grip"][:, None], -1).mean()
    loss = pos_loss + cfg.rot_weight * rot_loss + cfg.grip_weight * grip_loss
    return loss, {"pos": pos_loss, "rot": rot_loss, "grip": grip_loss}


def gripper_bins(amount: jax.Array) -> jax.Array:
    """Open amounts in [0, 1] -> the nearest of the GRIP_BINS levels (int32)."""
    return jnp.clip(jnp.round(amount * (GRIP_BINS - 1)), 0, GRIP_BINS - 1).astype(jnp.int32)


def predict(model: ReferenceVLA, views: jax.Array, ids: jax.Array, mask: jax.Array,
            gripper_open: jax.Array, step: jax.Array) -> tuple[jax.Array, jax.Array, jax.Array]:
    """World position (B, 3), Euler bins (B, 3) int32 and the gripper's open amount (B,)."""
    logits, rot, grip = model(views, ids, mask, gripper_open, step)
    return (decode_position(logits), jnp.argmax(rot, -1).astype(jnp.int32),
            jnp.argmax(grip, -1).astype(jnp.float32) / (GRIP_BINS - 1))
