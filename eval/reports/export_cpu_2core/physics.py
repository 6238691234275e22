"""Physics only (reset + expert, no rendering) per seen task: 3 batches of 4 demos, as the
export re-runs them; the first batch also builds the scene and compiles (setup_s).

    PYTHONPATH=. python eval/reports/export_cpu_2core/physics.py
"""

import time

import numpy as np

from agnostos_mjx.data.generate import demo_keys
from agnostos_mjx.infra.settings import configure_jax
from agnostos_mjx.runtime.env import Episodes
from agnostos_mjx.runtime.outcome import Outcome
from agnostos_mjx.tasks import parse_tasks

configure_jax()  # as the commands do, before JAX starts

out = {}
for task in parse_tasks("seen"):
    episodes = Episodes(task, "native")
    times, ok, key_actions = [], 0, 0
    for b in range(3):
        t = time.perf_counter()
        idx = np.arange(4 * b, 4 * b + 4)
        env = episodes.reset(demo_keys(0, task.name, idx, np.zeros(4, int)),
                             (idx % task.num_variations).astype(np.int32), stop_at_success=False)
        env = episodes.run_expert(env)
        times.append(time.perf_counter() - t)
        ok += int((env.outcome == Outcome.SUCCESS).sum())
        key_actions += int(env.key_actions.sum())
    out[task.name] = dict(setup_s=times[0] - np.mean(times[1:]),
                          per_demo_s=np.mean(times[1:]) / 4, key_actions=key_actions / 12,
                          success=ok)
    print(task.name, {k: round(float(v), 2) for k, v in out[task.name].items()}, flush=True)
print("mean per-demo physics s", np.mean([v["per_demo_s"] for v in out.values()]),
      "mean setup s", np.mean([v["setup_s"] for v in out.values()]),
      "mean key actions", np.mean([v["key_actions"] for v in out.values()]))
