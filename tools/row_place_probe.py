"""Whether a row's result depends on its place in a call, per GPU (or CPU) program.

    python tools/row_place_probe.py [--json OUT]

The selection's programs (encoder, DDIM sampler, the whole frames-to-scores program, the
similarity as a GEMM and as a reduction) run on one call of random frames (64 rows on a
GPU, 4 on the CPU) and again with the rows rotated by 5/8 of the call; the device planner
(`control.plan_arm`) runs a reset batch of 75 worlds alone and repeated in calls of 150,
600 and 1,800 rows.  Prints the largest change of a row's result for each.  Where a
program's rows move with their place, calls may mix the rows of several tasks only in an
order that timing cannot change (agnostos_mjx/infra/gather.py).  eval/reports/main_job_h100_native
has a GPU's table.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

from agnostos_mjx.infra.settings import configure_jax


def moved(fn, n: int) -> dict:
    """fn(order) -> (n, ...) results with rows in `order`: the change of each row's result
    when the rows come rotated by 5/8 of the call (40 of 64 places)."""
    order = np.roll(np.arange(n), max(1, 5 * n // 8))
    t0 = time.perf_counter()
    a = np.asarray(fn(np.arange(n)))
    b = np.asarray(fn(np.argsort(order)))[order]
    diff = np.abs(a - b).reshape(n, -1).max(1)
    return {"max_diff": float(diff.max()), "rows_changed": int((diff > 0).sum()), "rows": n,
            "s": round(time.perf_counter() - t0, 1)}


def selection_rows() -> dict:
    import jax
    import jax.numpy as jnp

    from agnostos_mjx.dynamics import pipeline as P
    from agnostos_mjx.dynamics.features import _normalise, _similarity
    from agnostos_mjx.policies.retrieval import RetrievalPolicy

    selector = RetrievalPolicy().selector
    pl = selector.pipeline
    n = pl.chunk_size
    rng = np.random.default_rng(0)
    frames = rng.integers(0, 255, (n, 128, 128, 3), np.uint8)
    texts = ["press the button", "open the drawer", "put the knife on the board"]
    instructions = [texts[i % 3] for i in range(n)]
    ids, mask = pl.tokens(instructions)
    (ae_graph, ae_state), (graph, state) = pl.ae_split, pl.model_split
    encode = jax.jit(lambda f: P._encode(ae_graph, ae_state, f) * pl.latent_scale)
    z = np.asarray(encode(frames))
    rows = [(frames[i], instructions[i]) for i in range(n)]
    bank = tuple(selector._bank.values())
    queries = tuple(_normalise(jnp.asarray(rng.standard_normal((n, b.shape[1]), np.float32)),
                               True) for b in bank)
    reduce = jax.jit(lambda qs, bs: sum(jnp.sum(q[:, None] * b[None], -1)
                                        for q, b in zip(qs, bs)) / len(qs))
    return {
        "encoder": moved(lambda o: encode(frames[o]), n),
        "sampler": moved(lambda o: P._sample(graph, state, pl.diffusion, jnp.asarray(z[o]),
                                             ids[o], mask[o]), n),
        "selection_program": moved(
            lambda o: np.stack(selector._similarities([rows[i] for i in o])), n),
        "similarity_gemm": moved(lambda o: _similarity(tuple(q[o] for q in queries), bank,
                                                       True), n),
        "similarity_reduce": moved(lambda o: reduce(tuple(q[o] for q in queries), bank), n),
    }


def planner_rows(sizes=(150, 600, 1800)) -> dict:
    import jax

    from agnostos_mjx.runtime.env import Episodes
    from agnostos_mjx.sim import control
    from agnostos_mjx.tasks import get_task

    ep = Episodes(get_task("put_knife_on_chopping_board"), "native", planner="host")
    env = ep.reset(jax.random.split(jax.random.PRNGKey(0), 75), np.zeros(75, np.int32))
    second = ep.expert_actions(env)
    q = np.asarray(env.data[:, ep.spec.arm_q], np.float32)
    pos, quat = (np.asarray(x[:, 1], np.float32) for x in (second.pos, second.quat))
    plan = control.jit_for_robot(control.plan_arm, ep.kin)
    alone = [np.asarray(x) for x in plan(q, pos, quat)]
    out = {}
    for size in sizes:
        shifts = [np.roll(np.arange(75), 17 * k) for k in range(size // 75)]
        idx = np.concatenate(shifts)
        res = [np.asarray(x) for x in plan(q[idx], pos[idx], quat[idx])]
        t0 = time.perf_counter()
        jax.block_until_ready(plan(q[idx], pos[idx], quat[idx]))
        ms = (time.perf_counter() - t0) * 1000
        diff = max(float(np.abs(r[k * 75:(k + 1) * 75][np.argsort(s)] - a).max())
                   for k, s in enumerate(shifts) for r, a in zip(res, alone))
        out[f"plan_arm_{size}"] = {"max_diff": diff, "ms_per_call": round(ms, 1)}
    return out


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--json", type=Path, help="also write the results here")
    args = p.parse_args()
    configure_jax()
    import jax

    result = {"device": str(jax.devices()[0]), **selection_rows(), **planner_rows()}
    print(json.dumps(result, indent=1))
    if args.json:
        args.json.write_text(json.dumps(result, indent=1))


if __name__ == "__main__":
    main()
