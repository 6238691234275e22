"""Tasks handed to ``--local-processes`` processes: each its balanced share, longest first,
then whatever another process has not started yet.

A fixed split (process I runs tasks I, I+N, ...) leaves processes idle while others still
work: in the main job on a 2 x H100 host, 16 processes had 1 or 2 of the 23 tasks each, and
the slowest needed 81.6 s of task time against a mean of 56.5 s
(docs/performance.md).  Here each process first takes its share of a split balanced by
`EXPECTED_S` (`claim_order`), then the next task no process has taken yet, longest first
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

# Expected seconds of each task's 75 episodes, by backend: shares are balanced by their sums;
# a task not listed counts as its backend's median.
# warp: the unseen tasks of the warm main job on a 2 x H100 host, without the ~10 s that a
# process's first task adds for compiling (timings.jsonl in eval/reports/main_job_h100_x2).
# native, unseen: the main job's CPU seconds, `python tools/task_cost.py RUN` on a warm H200
# run (its world-steps times the task's step under its expert on one core of a 2-core CPU,
# plus 12 s for 25 planning rounds; eval/reports/main_job_h200_native); native, seen: the
# reference VLA's evaluation on a 2 x H100 host (eval/reports/reference_vla), alike in scale.
EXPECTED_S = {
    "warp": {
        "put_toilet_roll_on_stand": 47, "put_knife_on_chopping_board": 44,
        "take_lid_off_saucepan": 44, "put_rubbish_in_bin": 44,
        "put_umbrella_in_umbrella_stand": 44, "straighten_rope": 43,
        "take_plate_off_colored_dish_rack": 39, "put_books_on_bookshelf": 38,
        "turn_oven_on": 37, "phone_on_base": 35, "basketball_in_hoop": 35,
        "unplug_charger": 33, "beat_the_buzz": 31, "open_grill": 30, "toilet_seat_down": 29,
        "water_plants": 28, "take_usb_out_of_computer": 27, "scoop_with_spatula": 27,
        "lamp_off": 27, "close_laptop_lid": 26, "close_microwave": 26, "lamp_on": 20,
        "close_fridge": 3,
    },
    "native": {
        "straighten_rope": 123, "water_plants": 48, "take_lid_off_saucepan": 43,
        "put_toilet_roll_on_stand": 39, "put_rubbish_in_bin": 28, "unplug_charger": 28,
        "take_plate_off_colored_dish_rack": 27, "basketball_in_hoop": 26,
        "put_books_on_bookshelf": 26, "scoop_with_spatula": 25,
        "put_umbrella_in_umbrella_stand": 24, "phone_on_base": 21,
        "put_knife_on_chopping_board": 21, "open_grill": 20, "turn_oven_on": 20,
        "take_usb_out_of_computer": 19, "beat_the_buzz": 17, "close_laptop_lid": 17,
        "close_microwave": 16, "toilet_seat_down": 16, "lamp_off": 14, "lamp_on": 14,
        "close_fridge": 1,
        # seen
        "place_cups": 75, "put_item_in_drawer": 65, "meat_off_grill": 64,
        "sweep_to_dustpan_of_size": 59, "stack_blocks": 57, "light_bulb_in": 54,
        "stack_cups": 52, "turn_tap": 52, "close_jar": 51, "slide_block_to_color_target": 48,
        "put_groceries_in_cupboard": 47, "reach_and_drag": 44,
        "place_shape_in_shape_sorter": 44, "put_money_in_safe": 43,
        "place_wine_at_rack_location": 40, "push_buttons": 37,
        "insert_onto_square_peg": 33, "open_drawer": 19,
    },
}


SEED_UNIT = "@"  # a unit of one seed of a task: "straighten_rope@1"
# Written by a process of a queue once its results are final: the launcher merges then,
# while the processes end (an interpreter's teardown takes 0.5 s and more).
FINISHED_FILE = "finished"


def unit_task(unit: str) -> tuple[str, int | None]:
    """(task, seed) of a queue unit; seed None for a whole task."""
    task, sep, seed = unit.partition(SEED_UNIT)
    return task, int(seed) if sep else None


def expected_s(names: Sequence[str], backend: str = "native") -> list[float]:
    """`EXPECTED_S` of each name on `backend` (a device backend counts as warp, a host one
    as native); the backend's median for a task not listed.  A task split into units of one
    seed (`split_by_seed`) is shared equally by its units in `names`."""
    table = EXPECTED_S["warp" if CAPABILITIES[backend].on_device else "native"]
    median = statistics.median(table.values())
    tasks = [unit_task(name)[0] for name in names]
    units = Counter(tasks)
    return [table.get(task, median) / units[task] for task in tasks]


# straighten_rope's process got ~1.8x the CPU time of the others (2.9 against 1.6 cores on
# one H200, its physics running while their threads waited on their policies): at 1.6 mean
# shares of 8 processes it ended before them, at 3.1 of 16 it ended the run.
ALONE_SHARES = 2.0


def split_by_seed(names: Sequence[str], backend: str, processes: int,
                  seeds: Sequence[int]) -> list[str]:
    """The queue's units of work: each task whole, or one unit per seed ("task@seed") for a
    task expected to take more than `ALONE_SHARES` mean shares of a process, which would end
    the run in its process alone (straighten_rope, ~20% of the main job's CPU work, on 16
    processes: its process ran 29.6 s, the others 22-28 s).  A world's episode does not
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
