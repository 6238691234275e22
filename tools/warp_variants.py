"""Device probe: which setting limits MJX-warp throughput at large batch?"""

import os
import sys
import time

import jax
import jax.numpy as jnp
import numpy as np
from mujoco import mjx

from agnostos_mjx.episode import Episodes
from agnostos_mjx.physics.mjx_backend import MjxBackend
from agnostos_mjx.tasks import get_task

B = int(sys.argv[1]) if len(sys.argv) > 1 else 1024
T = 100
ep = Episodes(get_task("lamp_on"), "native")
env = ep.reset(jax.random.split(jax.random.PRNGKey(0), B), np.zeros(B, int))
ctrl = np.repeat(np.asarray(env.physics.ctrl)[:, None], T, 1)


def timed(name, fn, *args):
    out = fn(*args)
    jax.block_until_ready(out)
    t = time.time()
    for _ in range(2):
        out = fn(*args)
    jax.block_until_ready(out)
    print(f"{name}: {2 * T * B / (time.time() - t):,.0f} env-steps/s", flush=True)


for cpw, nj in ((64, 256), (16, 64)):
    be = MjxBackend(ep.scene.model, "warp", contacts_per_world=cpw, constraints_per_world=nj)
    timed(f"scan contacts/world {cpw} njmax {nj}", be.run, env.physics, ctrl)

# Python loop over a jitted single step on persistent data (no scan, no make_data per call).
m = ep.scene.model
mx = mjx.put_model(m, impl="warp")
d = jax.vmap(lambda q: mjx.make_data(m, impl="warp", naconmax=B * 16, njmax=64).replace(qpos=q))(
    jnp.asarray(env.physics.qpos, jnp.float32))
d = d.replace(mocap_pos=jnp.asarray(env.physics.mocap_pos, jnp.float32),
              mocap_quat=jnp.asarray(env.physics.mocap_quat, jnp.float32),
              ctrl=jnp.asarray(env.physics.ctrl, jnp.float32))
step = jax.jit(jax.vmap(lambda d: mjx.step(mx, d)))


def loop(d):
    for _ in range(T):
        d = step(d)
    return d.qpos


timed("python loop of jitted vmapped step", loop, d)
scan = jax.jit(lambda d: jax.lax.scan(lambda d, _: (jax.vmap(lambda d: mjx.step(mx, d))(d), None),
                                       d, None, length=T)[0].qpos)
timed("scan of vmapped step, persistent data", scan, d)
print("ncon per world after settle:", float(jnp.mean(d._impl.nacon)) / B if hasattr(d._impl, "nacon") else "n/a")
os.makedirs(os.environ.get("OUT", "."), exist_ok=True)
