"""Where a process's start-up and first tasks go: run `python -m agnostos_mjx.eval ARGS` in
this process with JAX's tracing, lowering, compiling and persistent-cache events recorded,
then print them summed per function, count the programs, and write every event with its
time since start:

    python tools/compile_events.py --json events.json -- --tasks lamp_on --batch 75 ...

Tracing is paid in every process even when the compiled program comes from the disk cache;
programs that call Warp through the FFI are compiled in every process as well.
"""

from __future__ import annotations

import argparse
import atexit
import collections
import json
import runpy
import sys
import time

START = time.perf_counter()
# Every program a process runs is lowered once, whether XLA then compiles it or the
# persistent cache has it: lowerings count the programs.
LOWERED, COMPILED = "jaxpr_to_mlir_module_duration", "backend_compile_duration"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--json", help="write every event (name, function, seconds, at) here")
    parser.add_argument("--top", type=int, default=25, help="functions listed (default 25)")
    parser.add_argument("eval_args", nargs=argparse.REMAINDER,
                        help="-- then the arguments of python -m agnostos_mjx.eval")
    args = parser.parse_args()
    eval_args = args.eval_args[1:] if args.eval_args[:1] == ["--"] else args.eval_args

    from jax import monitoring

    events: list[dict] = []

    def on_duration(event: str, duration_secs: float, **kw) -> None:
        events.append({"event": event.rsplit("/", 1)[-1], "fun": str(kw.get("fun_name", "")),
                       "s": round(duration_secs, 4),
                       "at": round(time.perf_counter() - START, 2)})

    def on_event(event: str, **kw) -> None:
        events.append({"event": event.rsplit("/", 1)[-1], "fun": "", "s": 0.0,
                       "at": round(time.perf_counter() - START, 2)})

    monitoring.register_event_duration_secs_listener(on_duration)
    monitoring.register_event_listener(on_event)

    @atexit.register
    def report() -> None:
        wall = time.perf_counter() - START
        totals: dict[tuple[str, str], list[float]] = collections.defaultdict(lambda: [0, 0.0])
        for e in events:
            if e["s"]:
                totals[(e["event"], e["fun"])][0] += 1
                totals[(e["event"], e["fun"])][1] += e["s"]
        print(f"== process wall {wall:.1f} s", file=sys.stderr)
        by_event = collections.Counter()
        for (event, _), (_, s) in totals.items():
            by_event[event] += s
        for event, s in by_event.most_common():
            print(f"== {event}: {s:.1f} s", file=sys.stderr)
        for (event, fun), (n, s) in sorted(totals.items(), key=lambda x: -x[1][1])[:args.top]:
            print(f"== {s:7.2f} s {n:4d}x {event} {fun[:80]}", file=sys.stderr)
        lowered = [e["fun"] for e in events if e["event"] == LOWERED]
        compiled = sum(e["event"] == COMPILED for e in events)
        print(f"== programs: {len(lowered)} lowered, {compiled} of them compiled (the others "
              f"came from the persistent cache): {', '.join(sorted(lowered))}", file=sys.stderr)
        if args.json:
            with open(args.json, "w") as f:
                json.dump({"wall_s": round(wall, 2), "events": events}, f)

    sys.argv = ["agnostos_mjx.eval", *eval_args]
    runpy.run_module("agnostos_mjx.eval", run_name="__main__")


if __name__ == "__main__":
    main()
