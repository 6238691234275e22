"""Remote vs in-process policy cost: ``python -m agnostos_mjx.bench.remote_policy [--quick]``.

Runs the oracle on one batch of worlds per task twice, in process and through the
reference server (a separate process on loopback, preset ``sim``), after a warm-up batch
each, and prints key actions per second and the wall time the remote path adds per key
action (one world's action) and per step (one request per running world, concurrently).
Both runs execute the same episodes (checked), so the difference is the protocol's cost:
encoding, loopback round trips, the server's per-world mirror and policy call.
"""

from __future__ import annotations

import argparse
import re
import subprocess
import sys
import time
from collections.abc import Sequence

import numpy as np

from agnostos_mjx.infra.settings import configure_jax


def run_batch(runner, policy, batch: int, seed: int) -> tuple[float, int, int, np.ndarray]:
    """(seconds, key actions, steps, outcomes) of one batch of `policy` on `runner`."""
    from agnostos_mjx.evaluation.protocol import episode_keys, policy_seed
    from agnostos_mjx.policies.base import Round

    episodes = np.arange(batch)
    keys = episode_keys(np.full(batch, seed), episodes)
    variations = np.zeros(batch, np.int32)
    t0 = time.perf_counter()
    env = runner.reset(keys, variations)
    instructions = [runner.task.descriptions(0)[0]] * batch
    view = Round.for_policy(policy, runner, env, instructions,
                            [policy_seed(seed, e) for e in episodes])
    policy.reset(view)
    steps = 0
    for _ in range(runner.task.max_key_actions):
        if env.done.all():
            break
        env, _ = runner.step(env, policy.act(view.at(env)))
        steps += 1
    return time.perf_counter() - t0, int(env.key_actions.sum()), steps, env.outcome.copy()


def start_server() -> tuple[subprocess.Popen, str]:
    proc = subprocess.Popen([sys.executable, "-m", "agnostos_mjx.serve", "--policy", "oracle",
                             "--port", "0", "--quiet"], stdout=subprocess.PIPE, text=True)
    assert proc.stdout is not None
    line = proc.stdout.readline()
    match = re.search(r"ws://\S+", line)
    if not match:
        proc.kill()
        raise RuntimeError(f"the server did not start: {line!r}")
    return proc, match.group(0)


def main(argv: Sequence[str] | None = None) -> int:
    configure_jax()
    p = argparse.ArgumentParser(prog="python -m agnostos_mjx.bench.remote_policy")
    p.add_argument("--tasks", default="lamp_on,phone_on_base")
    p.add_argument("--batch", type=int, default=75)
    p.add_argument("--quick", action="store_true", help="lamp_on only")
    a = p.parse_args(argv)
    from agnostos_mjx.policies import make_policy
    from agnostos_mjx.runtime.env import Episodes
    from agnostos_mjx.tasks import get_task

    tasks = ["lamp_on"] if a.quick else a.tasks.split(",")
    server, url = start_server()
    try:
        rows = []
        for name in tasks:
            runner = Episodes(get_task(name), "native")
            res = {}
            for label, policy in (("in-process", make_policy("oracle")),
                                  ("remote", make_policy("remote", url=url))):
                run_batch(runner, policy, a.batch, seed=1)  # warm-up: compile, connect
                res[label] = run_batch(runner, policy, a.batch, seed=0)
            (t_l, k_l, s_l, o_l), (t_r, k_r, s_r, o_r) = res["in-process"], res["remote"]
            same = (k_l, s_l) == (k_r, s_r) and np.array_equal(o_l, o_r)
            assert same, "the remote episodes differ from the in-process ones"
            rows.append((name, k_l, s_l, k_l / t_l, k_r / t_r, 1000 * (t_r - t_l) / k_l,
                         1000 * (t_r - t_l) / s_l, t_l, t_r))
    finally:
        server.terminate()
        server.wait(10)
    print(f"oracle, batch {a.batch}, native MuJoCo on the CPU, server on loopback")
    print("| task | key actions | steps | in-process key actions/s | remote key actions/s | "
          "added ms per key action | added ms per step | wall s in-process / remote |")
    print("|---|---|---|---|---|---|---|---|")
    for name, k, s, kl, kr, per_key, per_step, tl, tr in rows:
        print(f"| {name} | {k} | {s} | {kl:.1f} | {kr:.1f} | {per_key:.2f} | {per_step:.1f} "
              f"| {tl:.2f} / {tr:.2f} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
