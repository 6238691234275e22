"""Where a reference-VLA training step's time goes, on synthetic data of the GPU recipe's shape.

    python tools/vla_step_profile.py [--batch 32] [--points 36864] [--iters 20] [--out F.json]

Times (best of --iters, after compiling): the virtual views alone (views.render_views), the
loss forward, and the whole training step (loss, gradient, AdamW) at JAX's default matmul
precision and with 'tensorfloat32' and 'bfloat16' matmuls: whether the views, the network
or the precision sets a step's time.  `VLA_PRECISION=auto bash train/vla_gpu.sh train` runs
it and trains at the fastest precision (by >10% over the default, else the default).
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
from flax import nnx

from agnostos_mjx.train.common import make_step, optimizer
from agnostos_mjx.train.vla import TRAIN_DEFAULT, batch_inputs
from agnostos_mjx.vla.model import VLA_DEFAULT, ReferenceVLA, vla_loss
from agnostos_mjx.vla.views import render_views


def best_of(fn, iters: int) -> float:
    jax.block_until_ready(fn())
    times = []
    for _ in range(iters):
        t = time.perf_counter()
        jax.block_until_ready(fn())
        times.append(time.perf_counter() - t)
    return min(times)


def main() -> None:
    from agnostos_mjx.infra.settings import configure_jax

    configure_jax()  # as the commands do, before JAX starts
    p = argparse.ArgumentParser(description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--batch", type=int, default=32)
    p.add_argument("--points", type=int, default=4 * 96 * 96, help="points per sample")
    p.add_argument("--iters", type=int, default=20)
    p.add_argument("--out", type=Path)
    args = p.parse_args()
    cfg, b, n = VLA_DEFAULT, args.batch, args.points
    rng = np.random.default_rng(0)
    batch = {"points": jnp.asarray(rng.uniform([-0.3, -0.5, 0.75], [0.7, 0.5, 1.75],
                                                (b, n, 3)).astype(np.float16)),
             "rgb": jnp.asarray(rng.integers(0, 255, (b, n, 3), dtype=np.uint8)),
             "gripper_pos": jnp.asarray(rng.uniform(0, 1, (b, 3)).astype(np.float32)),
             "gripper_open": jnp.ones(b), "step": jnp.zeros(b, jnp.int32),
             "target_pos": jnp.asarray(rng.uniform([-0.2, -0.4, 0.8], [0.6, 0.4, 1.5],
                                                   (b, 3)).astype(np.float32)),
             "target_rot": jnp.zeros((b, 3), jnp.int32), "target_grip": jnp.zeros(b, jnp.int32),
             "desc_start": jnp.zeros(b, jnp.int32), "desc_count": jnp.ones(b, jnp.int32)}
    ids = jnp.ones((1, cfg.text_len), jnp.int32)
    mask = jnp.ones((1, cfg.text_len), bool)
    key = jax.random.key(0)
    graphdef, params = nnx.split(ReferenceVLA(cfg, rngs=nnx.Rngs(0)))
    tx = optimizer(TRAIN_DEFAULT)  # the training's AdamW and schedule
    opt = tx.init(params)
    result = {"device": str(jax.devices()[0]), "batch": b, "points": n}

    views = jax.jit(lambda bt: render_views(bt["points"], bt["rgb"], bt["gripper_pos"],
                                            cfg.view_size))
    result["views_ms"] = 1e3 * best_of(lambda: views(batch), args.iters)
    inputs = jax.jit(lambda bt, k: batch_inputs(bt, k, ids, mask, cfg, 0.1))(batch, key)
    fwd = jax.jit(lambda pr, x: vla_loss(nnx.merge(graphdef, pr), x)[0])
    result["loss_forward_ms"] = 1e3 * best_of(lambda: fwd(params, inputs), args.iters)

    def loss_fn(model, bt, k):  # train_vla's
        return vla_loss(model, batch_inputs(bt, k, ids, mask, cfg, 0.1))[0]

    for precision in ("default", "tensorfloat32", "bfloat16"):
        with jax.default_matmul_precision(None if precision == "default" else precision):
            step = make_step(graphdef, tx, loss_fn)  # traced (at its first call) in here
            result[f"train_step_{precision}_ms"] = 1e3 * best_of(
                lambda step=step: step(params, opt, batch, key), args.iters)
        print(json.dumps(result), flush=True)
    if args.out:
        args.out.write_text(json.dumps(result, indent=2))


if __name__ == "__main__":
    main()
