"""Seconds a fresh process takes to import the dynamics pipeline and load the shipped model,
with `layers.cheap_tracer_attribute_errors` (how every run loads it) and without it (JAX's
error-message walk on every RNG draw of the constructors), alternately in new processes:

    python tools/load_time.py [--repeats 2] [--parallel 8] [--out load_time.json]

(`--parallel N`: N processes per measurement at once, as `--local-processes N` starts them;
each row then holds the slowest.)

Run on the machine whose start-up matters (each `--local-processes` child pays it once).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys

CHILD = r"""
import contextlib, json, sys, time
t0 = time.perf_counter()
import jax
from agnostos_mjx.dynamics import layers
from pathlib import Path
import agnostos_mjx
from agnostos_mjx.dynamics.pipeline import Pipeline
imported = time.perf_counter() - t0
if sys.argv[1] == "without":
    layers.cheap_tracer_attribute_errors = contextlib.nullcontext
t1 = time.perf_counter()
# the shipped model, as xicm.dynamics_selector.load_pipeline loads it (without mujoco)
Pipeline.load(Path(agnostos_mjx.__file__).parent / "assets" / "dynamics")
print(json.dumps({"import_s": round(imported, 2), "load_s": round(time.perf_counter() - t1, 2),
                  "jax": jax.__version__, "device": str(jax.devices()[0])}))
"""


def measure(mode: str, parallel: int = 1) -> dict:
    """One round of `parallel` fresh processes loading the model; the slowest one's times."""
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(
        p for p in (os.getcwd(), os.environ.get("PYTHONPATH", "")) if p))
    procs = [subprocess.Popen([sys.executable, "-c", CHILD, mode], stdout=subprocess.PIPE,
                              stderr=subprocess.PIPE, text=True, env=env)
             for _ in range(parallel)]
    rows = []
    for proc in procs:
        out, err = proc.communicate()
        if proc.returncode != 0:
            sys.exit(f"a {mode} child failed:\n{err[-2000:]}")
        rows.append(json.loads(out.strip().splitlines()[-1]))
    return max(rows, key=lambda r: r["import_s"] + r["load_s"]) | {"parallel": parallel}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--repeats", type=int, default=2, help="processes per mode (default 2)")
    parser.add_argument("--parallel", type=int, default=1,
                        help="processes started at once per measurement (default 1)")
    parser.add_argument("--out", help="write the results as JSON here")
    args = parser.parse_args(argv)
    if args.repeats < 1 or args.parallel < 1:
        parser.error("--repeats and --parallel must be >= 1")
    rows = []
    for _ in range(args.repeats):
        for mode in ("with", "without"):
            rows.append({"mode": mode, **measure(mode, args.parallel)})
            print(json.dumps(rows[-1]), flush=True)
    best = {m: min(r["load_s"] for r in rows if r["mode"] == m) for m in ("with", "without")}
    print(f"load the shipped dynamics model: {best['with']:.1f} s with the fix, "
          f"{best['without']:.1f} s without ({platform.node()}, {os.cpu_count()} cores)")
    if args.out:
        with open(args.out, "w") as f:
            json.dump({"rows": rows, "best_load_s": best, "cores": os.cpu_count()}, f, indent=1)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
