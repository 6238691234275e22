"""Tasks handed to ``--local-processes`` processes: each its balanced share, longest first,
then whatever another process has not started yet.

A fixed split (process I runs tasks I, I+N, ...) leaves processes idle while others still
work: with 1 or 2 tasks per process the slowest share sets the run's wall
(docs/performance.md, Task costs).  Here each process first takes its share of a split
balanced by the expected costs in task_costs.json (`claim_order`), then the next task no process has taken yet, longest first
(the short tasks fill the gaps at the end), so the run ends when the last task does.  A
task longer than two mean shares goes out by seed (`split_by_seed`), as units
``task@seed``.

A claim is a file ``<queue>/<unit>`` created with O_CREAT | O_EXCL (atomic on one machine's
file system) holding the claiming process's index.  The launcher empties the queue before
the processes start and, for ``--resume``, writes the claims of tasks a process already has
episodes of, so that the task stays with the process whose folder holds them.
"""

from __future__ import annotations

import errno
import functools
import json
import os
import statistics
from collections import Counter
from collections.abc import Generator, Sequence
from pathlib import Path
from typing import TypeVar

from agnostos_mjx.evaluation.config import UsageError
from agnostos_mjx.evaluation.records import EPISODES_FILE, load_records
from agnostos_mjx.physics import CAPABILITIES

T = TypeVar("T")

COSTS_FILE = Path(__file__).with_name("task_costs.json")  # tools/task_cost.py --write


@functools.cache
def expected_costs() -> dict[str, dict[str, float]]:
    """Each backend's expected seconds per task, from `COSTS_FILE`: data a measured run
    renews, not code (read once per process; no JAX)."""
    table = json.loads(COSTS_FILE.read_text())
    return {backend: table[backend] for backend in ("native", "warp")}


SEED_UNIT = "@"  # a unit of one seed of a task: "straighten_rope@1"
# Written by a process of a queue once its results are final: the launcher merges then,
# while the processes end (an interpreter's teardown is not free).
FINISHED_FILE = "finished"


def unit_task(unit: str) -> tuple[str, int | None]:
    """(task, seed) of a queue unit; seed None for a whole task."""
    task, sep, seed = unit.partition(SEED_UNIT)
    return task, int(seed) if sep else None


def expected_s(names: Sequence[str], backend: str = "native") -> list[float]:
    """`expected_costs` of each name on `backend` (a device backend counts as warp, a host
    one as native); the backend's median for a task not listed.  A task split into units of
    one seed (`split_by_seed`) is shared equally by its units in `names`."""
    table = expected_costs()["warp" if CAPABILITIES[backend].on_device else "native"]
    median = statistics.median(table.values())
    tasks = [unit_task(name)[0] for name in names]
    units = Counter(tasks)
    return [table.get(task, median) / units[task] for task in tasks]


# A process with one long task gets more CPU time than the others (its physics runs while
# their threads wait on their policies), so it may hold up to two mean shares before it ends
# the run alone (docs/performance.md, Task costs).
ALONE_SHARES = 2.0


def split_by_seed(names: Sequence[str], backend: str, processes: int,
                  seeds: Sequence[int]) -> list[str]:
    """The queue's units of work: each task whole, or one unit per seed ("task@seed") for a
    task expected to take more than `ALONE_SHARES` mean shares of a process, which would end
    the run in its process alone (straighten_rope, ~20% of the main job's CPU work, on 16
    processes).  A world's episode does not
    depend on the others in its batch, so the records do not change but for `batch_size`."""
    if processes < 2 or len(seeds) < 2:
        return list(names)
    cost = expected_s(names, backend)
    limit = ALONE_SHARES * sum(cost) / processes
    return [unit for name, c in zip(names, cost)
            for unit in ([f"{name}{SEED_UNIT}{s}" for s in seeds] if c > limit else [name])]


def longest_first(names: Sequence[str], backend: str = "native") -> list[int]:
    """Indices of `names` by expected time on `backend`, longest first; ties keep the given
    order."""
    cost = expected_s(names, backend)
    return sorted(range(len(names)), key=lambda i: -cost[i])


def balanced_shares(names: Sequence[str], backend: str, processes: int) -> list[list[int]]:
    """Indices of `names` split over `processes`: longest first, each task to the process
    with the least expected time so far (each share longest first)."""
    cost = expected_s(names, backend)
    totals = [0.0] * processes
    shares: list[list[int]] = [[] for _ in range(processes)]
    for i in longest_first(names, backend):
        p = min(range(processes), key=lambda p: (totals[p], p))
        totals[p] += cost[i]
        shares[p].append(i)
    return shares


def claim_order(names: Sequence[str], backend: str, processes: int, process_id: int,
                overlap: int = 1) -> list[int]:
    """Indices of `names` in the order process `process_id` of `processes` (running
    `overlap` tasks at once) tries to claim them: its `balanced_shares` share, then, longest
    first, the tasks of other shares that their process would start only once one of its
    first `overlap` has ended, for when this process runs out first.

    Taking the next task as processes free up balances nothing when every process starts
    `overlap` tasks at once (23 tasks, 8 processes x 3): whichever process started first
    took the 3 longest, and its tasks' physics take turns on its cores.  A process's first
    `overlap` tasks are its own alone, so a process with a short share cannot take them
    before their process has started."""
    shares = balanced_shares(names, backend, processes)
    later = {i for share in shares for i in share[overlap:]}
    mine = shares[process_id]
    return mine + [i for i in longest_first(names, backend) if i in later and i not in mine]


def prepare(queue: Path, out: Path, processes: int) -> dict[str, int]:
    """Empty `queue` and claim, for each process I < `processes`, the tasks it already has
    episodes of in ``out/proc-I``, whole and by seed (`split_by_seed`'s units; a unit found
    in several keeps the lowest I).  Returns those claims."""
    queue.mkdir(parents=True, exist_ok=True)
    for f in queue.iterdir():
        f.unlink()
    owners: dict[str, int] = {}
    for i in range(processes):
        for r in load_records(out / f"proc-{i}" / EPISODES_FILE):
            owners.setdefault(r["task"], i)
            owners.setdefault(f"{r['task']}{SEED_UNIT}{r['seed']}", i)
    for task, i in owners.items():
        (queue / task).write_text(str(i))
    return owners


class TaskQueue:
    """This process's view of the shared queue folder."""

    def __init__(self, directory: Path, process_id: int):
        if not Path(directory).is_dir():
            raise UsageError(f"--task-queue {directory}: no such folder (--local-processes "
                             "makes it)")
        self.directory, self.process_id = Path(directory), process_id
        self.mine: list[str] = []

    def _ours(self, task: str) -> bool:
        """Whether `task`'s claim file names this process."""
        path = self.directory / task
        return path.is_file() and path.read_text().strip() == str(self.process_id)

    def held(self, names: Sequence[str]) -> list[str]:
        """Those of `names` claimed for this process already (a resumed run's tasks)."""
        return [n for n in names if self._ours(n)]

    def claim(self, task: str) -> bool:
        """Take `task` unless another process has; True when it is this process's."""
        path = self.directory / task
        try:
            fd = os.open(path, os.O_CREAT | os.O_EXCL | os.O_WRONLY, 0o644)
        except OSError as err:
            if err.errno != errno.EEXIST:
                raise
            ours = self._ours(task)
        else:
            with os.fdopen(fd, "w") as f:
                f.write(str(self.process_id))
            ours = True
        if ours and task not in self.mine:
            self.mine.append(task)
        return ours

    def claimed(self, task: str, steps: Generator[T, object, list]
                ) -> Generator[T, object, list]:
        """`steps` (rollout.task_steps, not started yet) if this process gets `task`, else
        nothing: the claim is made when the scheduler starts the job, i.e. when this process
        is free for it."""
        if not self.claim(task):
            steps.close()
            return []
        return (yield from steps)
