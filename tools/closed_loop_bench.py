"""How fast the evaluator's closed loop runs for an image policy, against its bare renderer.

Runs ``agnostos-eval --policy timing`` (a policy that declares cameras and answers at once,
agnostos_mjx/policies/timing.py) as a user types it, once per renderer route, and reads the
run's timings.jsonl: wall seconds, control steps per second, camera frames per second while
rendering, and the tasks' time split into render, policy, physics and other.  In the same
process it then times the bare renderer (the route's render call on a reset batch of the
first task) so that the loop's frame rate reads as a share of what the renderer can do.

    python tools/closed_loop_bench.py                       # the 3-task dense run, 75 worlds
    python tools/closed_loop_bench.py --renderers cpu,auto  # before / after on a GPU host
    python tools/closed_loop_bench.py --quick               # a CPU-sized check
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

DEFAULT_TASKS = "lamp_on,close_microwave,put_knife_on_chopping_board"


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    p = argparse.ArgumentParser(prog="python tools/closed_loop_bench.py", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--tasks", default=DEFAULT_TASKS, help="tasks of the run (comma-separated)")
    p.add_argument("--batch", type=int, default=75, help="worlds at once (= episodes a task)")
    p.add_argument("--action-mode", default="dense", choices=("dense", "keyaction"),
                   help="the policy's action mode")
    p.add_argument("--dense-steps", type=int, default=300,
                   help="control steps every episode runs (dense mode)")
    p.add_argument("--chunk", type=int, default=1,
                   help="rows per answer: the policy is asked every CHUNK control steps")
    p.add_argument("--cameras", default="front,wrist", help="cameras the policy declares")
    p.add_argument("--size", type=int, default=128, help="image height and width in pixels")
    p.add_argument("--renderers", default="auto",
                   help="routes to run, comma-separated: auto (as a user types it), cpu, warp")
    p.add_argument("--bare-repeats", type=int, default=5,
                   help="timed calls of the bare renderer (after one untimed warm-up call)")
    p.add_argument("--extra", default="",
                   help="further agnostos-eval flags, e.g. '--local-processes 3'")
    p.add_argument("--json", type=Path, help="write the figures here as JSON")
    p.add_argument("--keep", type=Path, help="keep the runs' folders under this folder")
    p.add_argument("--quick", action="store_true",
                   help="a CPU-sized run: lamp_on, 4 worlds, 20 control steps, 64 px, cpu")
    args = p.parse_args(argv)
    if args.quick:
        args.tasks, args.batch, args.dense_steps, args.size = "lamp_on", 4, 20, 64
        args.renderers, args.bare_repeats = "cpu", 2
    for flag in ("batch", "dense_steps", "chunk", "size", "bare_repeats"):
        if getattr(args, flag) < 1:
            p.error(f"--{flag.replace('_', '-')} must be at least 1")
    return args


def eval_command(args: argparse.Namespace, renderer: str, out: Path) -> list[str]:
    """The evaluation as a user types it (no --renderer for auto)."""
    cmd = [sys.executable, "-m", "agnostos_mjx.eval", "--policy", "timing",
           "--policy-arg", f"cameras={args.cameras}", "--policy-arg", f"size={args.size}",
           "--policy-arg", f"chunk={args.chunk}", "--action-mode", args.action_mode,
           "--tasks", args.tasks, "--seeds", "0", "--episodes", str(args.batch),
           "--batch", str(args.batch), "--quiet", "--out", str(out)]
    if args.action_mode == "dense":
        cmd += ["--dense-steps", str(args.dense_steps)]
    if renderer != "auto":
        cmd += ["--renderer", renderer]
    return cmd + args.extra.split()


def run_loop(args: argparse.Namespace, renderer: str, out: Path) -> dict:
    """One evaluation: its wall time and the sums of its tasks' timings."""
    t = time.perf_counter()
    subprocess.run(eval_command(args, renderer, out), check=True)
    wall = time.perf_counter() - t
    lines = [json.loads(x) for f in [out / "timings.jsonl", *out.glob("proc-*/timings.jsonl")]
             if f.is_file() for x in f.read_text().splitlines() if x]
    tasks = [r for r in lines if "task" in r]
    total = {k: sum(r.get(k, 0.0) for r in tasks)
             for k in ("build_s", "reset_s", "render_s", "policy_s", "physics_s",
                       "other_s", "frames", "rounds", "world_steps")}
    results = json.loads((out / "results.json").read_text())
    steps = sum(r["rounds"] * args.batch for r in tasks)  # control steps of all worlds
    # The run's own clock starts when its launcher starts the processes and stops at the
    # merge; the rest of the command's wall is start-up and teardown around it.
    return {"renderer": renderer, "route": results.get("renderer"), "wall_s": round(wall, 2),
            "run_wall_s": results.get("wall_s"),
            "tasks_s": round(sum(r["wall_s"] for r in tasks), 2),
            "control_steps_per_s": round(steps / wall, 1),
            "frames_per_render_s": round(total["frames"] / max(total["render_s"], 1e-9), 1),
            **{k: round(v, 2) for k, v in total.items()}}


def bare_renderer(args: argparse.Namespace, route: str) -> dict:
    """Frames/s of the route's bare render call, and of the whole observation, on a reset
    batch of the first task (the same cameras and size as the loop)."""
    import jax
    import numpy as np

    from agnostos_mjx.runtime.env import Episodes
    from agnostos_mjx.runtime.observation import ObservationSpec
    from agnostos_mjx.tasks import get_task

    runner = Episodes(get_task(args.tasks.split(",")[0]), "native", renderer=route)
    env = runner.reset(jax.random.split(jax.random.PRNGKey(0), args.batch),
                       np.zeros(args.batch, np.int32))
    spec = ObservationSpec(cameras=tuple(args.cameras.split(",")), height=args.size,
                           width=args.size, renderer=route)
    figures = {}
    for name, call in (("bare", lambda: jax.block_until_ready(
            runner.observer.render_views(env, spec))),
                       ("observation", lambda: runner.observe(env, spec))):
        call()  # builds the renderer and compiles
        t = time.perf_counter()
        for _ in range(args.bare_repeats):
            call()
        seconds = (time.perf_counter() - t) / args.bare_repeats
        figures[f"{name}_frames_per_s"] = round(args.batch * len(spec.cameras) / seconds, 1)
    runner.close()
    return figures


def table(rows: list[dict]) -> str:
    head = ["renderer", "route", "wall s", "run's own wall s", "control steps/s",
            "frames/s rendering",
            "bare renderer frames/s", "render s", "policy s", "physics s", "other s"]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for r in rows:
        lines.append("| " + " | ".join(str(x) for x in (
            r["renderer"], r["route"], r["wall_s"], r["run_wall_s"], r["control_steps_per_s"],
            r["frames_per_render_s"], r.get("bare_frames_per_s", ""), r["render_s"],
            r["policy_s"], r["physics_s"], r["other_s"])) + " |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        root = args.keep or Path(tmp)
        for renderer in args.renderers.split(","):
            row = run_loop(args, renderer, root / f"loop_{renderer}")
            if row["route"]:
                row.update(bare_renderer(args, row["route"]))
            rows.append(row)
            print(json.dumps(row), flush=True)
    print(table(rows))
    if args.json:
        args.json.write_text(json.dumps({"args": vars(args) | {"json": str(args.json),
                                                                "keep": str(args.keep)},
                                         "rows": rows}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
