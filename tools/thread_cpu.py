"""CPU seconds of each thread of a command's processes (Linux), to see where a run's CPU
time goes beside its physics.

    python tools/thread_cpu.py OUT.json -- python -m agnostos_mjx.eval ...

Runs the command and samples /proc/PID/task/*/stat of it and its descendants every 0.5 s
(a thread's last sample counts), then writes {pid: {tid: [name, cpu_s]}} to OUT.json and
prints each process's threads that used a second or more, numbered by start order
(MuJoCo's rollout pool shows as a run of equal threads).
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time

TICK = os.sysconf("SC_CLK_TCK")


def _descendants(root: int) -> list[int]:
    children: dict[int, list[int]] = {}
    for entry in os.listdir("/proc"):
        if entry.isdigit():
            try:
                stat = open(f"/proc/{entry}/stat").read()
            except OSError:
                continue
            parent = int(stat[stat.rindex(")") + 2:].split()[1])
            children.setdefault(parent, []).append(int(entry))
    found, todo = [], [root]
    while todo:
        pid = todo.pop()
        found.append(pid)
        todo += children.get(pid, [])
    return found


def main() -> None:
    if len(sys.argv) < 4 or sys.argv[2] != "--":
        sys.exit(__doc__)
    out, command = sys.argv[1], sys.argv[3:]
    proc = subprocess.Popen(command)
    seen: dict[str, dict[str, list]] = {}
    while proc.poll() is None:
        for pid in _descendants(proc.pid):
            try:
                for tid in os.listdir(f"/proc/{pid}/task"):
                    stat = open(f"/proc/{pid}/task/{tid}/stat").read()
                    fields = stat[stat.rindex(")") + 2:].split()
                    name = stat[stat.index("(") + 1: stat.rindex(")")]
                    seen.setdefault(str(pid), {})[tid] = [
                        name, (int(fields[11]) + int(fields[12])) / TICK]
            except OSError:
                continue
        time.sleep(0.5)
    with open(out, "w") as f:
        json.dump(seen, f)
    for pid, threads in seen.items():
        rows = sorted(threads.items(), key=lambda kv: int(kv[0]))
        total = sum(cpu for _, cpu in threads.values())
        big = [f"#{k} {cpu:.1f}" for k, (_, (_, cpu)) in enumerate(rows) if cpu >= 1.0]
        print(f"process {pid}: {len(rows)} threads, {total:.1f} CPU-s; " + ", ".join(big))
    sys.exit(proc.returncode)


if __name__ == "__main__":
    main()
