"""Device probe: where does MjxBackend.run lose MJX-warp throughput at large batch?"""

import sys
import time

import jax
import jax.numpy as jnp
import numpy as np
from mujoco import mjx

from agnostos_mjx.physics.mjx_backend import MjxBackend
from agnostos_mjx.runtime.env import Episodes
from agnostos_mjx.tasks import get_task

B = int(sys.argv[1]) if len(sys.argv) > 1 else 1024
ONLY_BACKEND = len(sys.argv) > 2
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
    return out


for mode in ("WARP", "WARP_STAGED"):
    be = MjxBackend(ep.scene.model, "warp", graph_mode=mode)
    _, sens = timed(f"MjxBackend.run graph_mode={mode}", be.run, env.physics, ctrl)
    print("  sensordata finite:", bool(np.isfinite(np.asarray(sens)).all()),
          "arm_q max |change| over the hold:",
          float(np.abs(np.asarray(sens)[:, -1, :7] - np.asarray(env.obs.data)[:, :7]).max()),
          flush=True)

if ONLY_BACKEND:
    sys.exit(0)
m = ep.scene.model
mx = mjx.put_model(m, impl="warp")
d = jax.jit(jax.vmap(lambda _: mjx.make_data(m, impl="warp", naconmax=B * 64, njmax=256)))(
    jnp.arange(B))
d = d.replace(qpos=jnp.asarray(env.physics.qpos, jnp.float32),
              mocap_pos=jnp.asarray(env.physics.mocap_pos, jnp.float32),
              mocap_quat=jnp.asarray(env.physics.mocap_quat, jnp.float32),
              ctrl=jnp.asarray(env.physics.ctrl, jnp.float32))
vstep = jax.vmap(lambda d: mjx.step(mx, d))
vstep_u = jax.vmap(lambda d, u: mjx.step(mx, d.replace(ctrl=u)))
us = jnp.swapaxes(jnp.asarray(ctrl, jnp.float32), 0, 1)
timed("scan, carry only", jax.jit(lambda d: jax.lax.scan(
    lambda d, _: (vstep(d), None), d, None, length=T)[0].qpos), d)
timed("scan, ctrl xs", jax.jit(lambda d, us: jax.lax.scan(
    lambda d, u: (vstep_u(d, u), None), d, us)[0].qpos), d, us)
timed("(default graph mode) scan, ctrl xs + sensordata ys", jax.jit(lambda d, us: jax.lax.scan(
    lambda d, u: (lambda n: (n, n.sensordata))(vstep_u(d, u)), d, us)[1]), d, us)
