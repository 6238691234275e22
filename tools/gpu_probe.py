"""One GPU session: warp vs native steps/s on one task, and oracle episodes on
warp for the four first tasks.  Run on the lent device (see README)."""

import json
import os
import sys
import time

import jax
import numpy as np

from agnostos_mjx.runtime.env import Episodes
from agnostos_mjx.runtime.outcome import Outcome
from agnostos_mjx.tasks import get_task

out = {"devices": [str(d) for d in jax.devices()]}
task = get_task(sys.argv[1] if len(sys.argv) > 1 else "lamp_on")
steps = 200
for backend in ("warp", "native"):
    ep = Episodes(task, backend)
    for batch in (75, 1024, 8192):
        if backend == "native" and batch > 75 and os.environ.get("SKIP_NATIVE_BIG"):
            continue
        env = ep.reset(jax.random.split(jax.random.PRNGKey(0), batch), np.zeros(batch, int))
        ctrl = np.repeat(np.asarray(env.physics.ctrl)[:, None], steps, 1)
        st, sens = ep.backend.run(env.physics, ctrl)  # warm-up / compile
        jax.block_until_ready(sens)
        t = time.time()
        for _ in range(3):
            st, sens = ep.backend.run(st, ctrl)
        jax.block_until_ready(sens)
        sps = 3 * steps * batch / (time.time() - t)
        out[f"{backend}_b{batch}_steps_per_s"] = sps
        print(backend, batch, f"{sps:,.0f} env-steps/s", flush=True)
for name in os.environ.get("ORACLE_TASKS", "lamp_on,close_microwave,open_drawer,push_buttons").split(","):
    if not name:
        continue
    for backend in ("warp", "native"):
        ep = Episodes(get_task(name), backend)
        b = 75
        keys = jax.vmap(lambda s, e: jax.random.fold_in(jax.random.PRNGKey(s), e))(
            np.repeat(np.arange(3), 25), np.tile(np.arange(25), 3))
        nvar = ep.task.num_variations
        var = np.asarray(jax.vmap(lambda k, n=nvar: jax.random.randint(
            jax.random.fold_in(k, 1), (), 0, n))(keys))
        t = time.time()
        env = ep.reset(keys, var)
        env = ep.run_expert(env)
        rate = float(np.mean(env.outcome == Outcome.SUCCESS))
        out[f"oracle_{name}_{backend}"] = rate
        print(name, backend, f"success {rate:.3f}", f"{time.time() - t:.1f}s", flush=True)
os.makedirs(os.environ.get("OUT", "."), exist_ok=True)
json.dump(out, open(os.path.join(os.environ.get("OUT", "."), "gpu_probe.json"), "w"), indent=1)
