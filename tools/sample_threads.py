"""Where the wall time of every thread of a command's Python processes goes (a small py-spy
that needs nothing installed): each process records every thread's stack every few
milliseconds and writes it at exit; then a summary per process and thread.

    python tools/sample_threads.py OUT -- python -m agnostos_mjx.eval ...
    python tools/sample_threads.py OUT --report-only        # summarise OUT again
    python tools/sample_threads.py OUT --py-spy RAW --rate 200   # summarise py-spy's samples

Where observations render through MJX-Warp (a GPU host), use py-spy instead (``py-spy record
--subprocesses --idle --threads -r 200 -f raw -o RAW -- CMD``, then ``--py-spy RAW``): under
this sampler Warp's CUDA-graph captures failed in a 3-task run's processes ("unknown capture
stream"), likely because it holds the threads' frames for an instant, so that a frame ending
meanwhile is freed on the sampler's thread with its arrays, mid-capture.

The command runs with OUT/site first on PYTHONPATH, whose ``sitecustomize`` starts the
sampler in every Python process the command starts (the evaluator's workers included) and
then loads the next ``sitecustomize`` on the path, if any.  A process's samples are written
to OUT/samples/PID.txt as collapsed stacks (``thread;file:function;... seconds``) at exit,
os._exit included (the evaluator's processes end that way).  The summary gives each thread's
seconds in the project's functions (inclusive) and in the innermost frames.
"""

from __future__ import annotations

import argparse
import collections
import os
import subprocess
import sys
from pathlib import Path

SITE = '''
import os, sys
_dir = os.environ.get("SAMPLE_THREADS_DIR")
if _dir:
    import atexit, collections, threading, time
    _seconds = collections.Counter()
    _names = {}
    _stopped = False
    _t0 = time.perf_counter()

    def _loop(interval=float(os.environ.get("SAMPLE_THREADS_INTERVAL", "0.005"))):
        me, last = threading.get_ident(), time.perf_counter()
        while not _stopped:
            time.sleep(interval)
            now = time.perf_counter()
            dt, last = now - last, now
            for th in threading.enumerate():
                _names[th.ident] = th.name
            for ident, frame in sys._current_frames().items():
                if ident == me:
                    continue
                parts = []
                while frame is not None:
                    code = frame.f_code
                    parts.append("/".join(code.co_filename.split("/")[-2:]) + ":" + code.co_name)
                    frame = frame.f_back
                parts.append(_names.get(ident, str(ident)))
                _seconds[";".join(reversed(parts))] += dt

    def _dump():
        global _stopped
        if _stopped:
            return
        _stopped = True
        os.makedirs(_dir, exist_ok=True)
        with open(os.path.join(_dir, f"{os.getpid()}.txt"), "w") as f:
            f.write(f"# {' '.join(sys.argv)[:300]} | wall {time.perf_counter() - _t0:.2f} s\\n")
            for stack, s in _seconds.most_common():
                f.write(f"{stack} {s:.4f}\\n")

    threading.Thread(target=_loop, name="thread-sampler", daemon=True).start()
    atexit.register(_dump)
    _exit = os._exit

    def _exit_after_dump(code):
        _dump()
        _exit(code)

    os._exit = _exit_after_dump

# the next sitecustomize on the path (an image's own), as if this one were not there
_here = os.path.dirname(os.path.abspath(__file__))
sys.modules.pop("sitecustomize", None)
_path, sys.path[:] = sys.path[:], [p for p in sys.path if os.path.abspath(p or ".") != _here]
try:
    import sitecustomize  # noqa: F401
except ImportError:
    pass
finally:
    sys.path[:] = _path
'''
PROJECT = ("agnostos_mjx", "evaluation", "runtime", "render", "physics", "policies", "infra",
           "sim", "data", "xicm", "dynamics", "vla", "remote", "tools")


def summarise(samples: Path, min_s: float = 0.3) -> str:
    """Per process and thread (>= min_s): project frames' inclusive seconds, then the
    innermost frames'."""
    lines = []
    for path in sorted(samples.glob("*.txt")):
        rows = path.read_text().splitlines()
        lines.append(f"== {path.stem}: {rows[0].lstrip('# ')}")
        total, inner, incl = collections.Counter(), collections.Counter(), collections.Counter()
        for row in rows[1:]:
            stack, seconds = row.rsplit(" ", 1)
            frames, s = stack.split(";"), float(seconds)
            thread = frames[0]
            total[thread] += s
            inner[thread, frames[-1]] += s
            for frame in dict.fromkeys(frames[1:]):
                if frame.split("/")[0] in PROJECT:
                    incl[thread, frame] += s
        for thread, s in total.most_common():
            if s < min_s:
                continue
            lines.append(f"  thread {thread}: {s:.1f} s")
            lines += [f"    {v:6.2f} s  {f}" for (t, f), v in incl.most_common()
                      if t == thread and v >= min_s]
            lines.append("    innermost:")
            lines += [f"    {v:6.2f} s  {f}" for (t, f), v in inner.most_common()
                      if t == thread and v >= min_s][:6]
    return "\n".join(lines)


def from_py_spy(raw: Path, samples: Path, rate: float) -> None:
    """py-spy's raw output (``--subprocesses --threads``: ``process P:"cmd";thread (T):
    name;func (path:line);... count``) as this sampler's files, one per process in
    `samples`: the same summary for both."""
    import re

    per: dict[str, collections.Counter] = collections.defaultdict(collections.Counter)
    argv: dict[str, str] = {}
    text = raw.read_text(errors="replace")
    for m in re.finditer(r'^(process \d+:.*?) (\d+)$', text, re.M | re.S):
        frames = m.group(1).split(";")
        procs = [f for f in frames if f.startswith("process ")]
        pid, _, cmd = procs[-1][len("process "):].partition(":")
        argv[pid] = cmd.strip('"').replace("\n", " ")
        thread = next((f.split(": ", 1)[-1] for f in frames if f.startswith("thread ")), "?")
        calls = []
        for f in frames:
            call = re.fullmatch(r"(.*) \((.*?)(?::\d+)?\)", f)
            if call and not f.startswith(("process ", "thread ")):
                calls.append("/".join(call.group(2).split("/")[-2:]) + ":" + call.group(1))
        per[pid][";".join([thread, *calls])] += int(m.group(2)) / rate
    samples.mkdir(parents=True, exist_ok=True)
    for pid, stacks in per.items():
        lines = [f"# {argv[pid][:300]} | py-spy"]
        lines += [f"{stack} {s:.4f}" for stack, s in stacks.most_common()]
        (samples / f"{pid}.txt").write_text("\n".join(lines) + "\n")


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    command = argv[argv.index("--") + 1:] if "--" in argv else []
    p = argparse.ArgumentParser(description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("out", type=Path, help="folder for the sampler's site and the samples")
    p.add_argument("--interval", type=float, default=0.005, help="seconds between samples")
    p.add_argument("--min-s", type=float, default=0.3,
                   help="leave out threads and frames under this many seconds")
    p.add_argument("--report-only", action="store_true",
                   help="summarise OUT/samples without running anything")
    p.add_argument("--py-spy", type=Path, metavar="RAW",
                   help="py-spy's raw output (--subprocesses --threads -f raw) to summarise: "
                        "written to OUT/samples first, nothing run")
    p.add_argument("--rate", type=float, default=100.0,
                   help="py-spy's samples per second (its -r; default 100, py-spy's own)")
    a = p.parse_args(argv[:argv.index("--")] if "--" in argv else argv)
    if a.py_spy is not None:
        if not a.py_spy.is_file():
            p.error(f"no such file: {a.py_spy}")
        from_py_spy(a.py_spy, a.out / "samples", a.rate)
    elif not a.report_only:
        if not command:
            p.error("give the command after --")
        site = a.out / "site"
        site.mkdir(parents=True, exist_ok=True)
        (site / "sitecustomize.py").write_text(SITE)
        env = {**os.environ, "SAMPLE_THREADS_DIR": str((a.out / "samples").resolve()),
               "SAMPLE_THREADS_INTERVAL": str(a.interval),
               "PYTHONPATH": os.pathsep.join(filter(None, [str(site.resolve()),
                                                           os.environ.get("PYTHONPATH")]))}
        code = subprocess.call(command, env=env)
        if code:
            print(f"the command exited with {code}", file=sys.stderr)
    if not (a.out / "samples").is_dir():
        p.error(f"no samples in {a.out}")
    print(summarise(a.out / "samples", a.min_s))
    return 0


if __name__ == "__main__":
    sys.exit(main())
