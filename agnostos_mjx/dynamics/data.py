"""What the dynamics model trains on: first and last front-camera frames of demos.

The demonstration bank (issue 5) yields one record per demo; `FramePairs.from_records`
turns any iterable of them into arrays.  `synthetic` makes a stand-in with the
same shapes in which the instruction decides how a shape moves, so the whole
pipeline is testable without the bank.
"""

from __future__ import annotations

import os
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from agnostos_mjx.dynamics.config import FRAME_SIZE


@dataclass(frozen=True)
class FramePairs:
    """N demos: first and last RGB frames (uint8, N x 128 x 128 x 3), instruction, task."""

    first: np.ndarray
    last: np.ndarray
    instructions: list[str]
    tasks: list[str]

    def __post_init__(self) -> None:
        n = len(self.first)
        shape = (n, FRAME_SIZE, FRAME_SIZE, 3)
        if self.first.shape != shape or self.last.shape != shape:
            raise ValueError(
                f"frames must be {shape}, got {self.first.shape} and {self.last.shape}"
            )
        if self.first.dtype != np.uint8 or self.last.dtype != np.uint8:
            raise ValueError("frames must be uint8")
        if len(self.instructions) != n or len(self.tasks) != n:
            raise ValueError("one instruction and one task name per demo")

    def __len__(self) -> int:
        return len(self.first)

    def subset(self, idx: np.ndarray | list[int]) -> FramePairs:
        idx = np.asarray(idx, dtype=int)
        return FramePairs(
            self.first[idx],
            self.last[idx],
            [self.instructions[i] for i in idx],
            [self.tasks[i] for i in idx],
        )

    def split(self, holdout_every: int) -> tuple[FramePairs, FramePairs]:
        """(train, held-out): demo i is held out when i % holdout_every == holdout_every - 1.

        By index, not at random, so every run and every machine agree on the split
        and a bank ordered by task holds out a slice of every task."""
        held = np.arange(len(self)) % holdout_every == holdout_every - 1
        return self.subset(np.flatnonzero(~held)), self.subset(np.flatnonzero(held))

    @classmethod
    def from_bank(cls, root: str | Path, camera: str = "front") -> FramePairs:
        """All demos of a demonstration bank directory (agnostos_mjx.data), task by task."""
        from agnostos_mjx.data import DemoBank  # the bank is optional for this package

        first, last, instructions, tasks = DemoBank(root).frame_pairs(camera)
        return cls(
            np.asarray(first, np.uint8), np.asarray(last, np.uint8), list(instructions), list(tasks)
        )

    @classmethod
    def from_records(cls, records: Iterable[Any], camera: str = "front") -> FramePairs:
        """Build from records (attributes or mapping keys): `instruction`, `task`
        (or `task_name`), and the frames as `frames[camera] = (first, last)` (the
        bank's Demo) or as `first`/`first_frame` and `last`/`last_frame`."""
        first, last, instr, tasks = [], [], [], []
        for r in records:
            frames = _get(r, "frames", default={})
            if camera in frames:
                f, g = frames[camera]
            else:
                f, g = (
                    _get(r, "first", "first_frame", "first_rgb"),
                    _get(r, "last", "last_frame", "last_rgb"),
                )
            first.append(np.asarray(f, np.uint8))
            last.append(np.asarray(g, np.uint8))
            instr.append(str(_get(r, "instruction", "lang_goal")))
            tasks.append(str(_get(r, "task", "task_name")))
        if not first:
            raise ValueError("no records")
        return cls(np.stack(first), np.stack(last), instr, tasks)

    def save(self, path: str | Path) -> None:
        """Compressed .npz, written to a temporary file and renamed (atomic)."""
        path = Path(path)
        tmp = path.with_name(path.name + ".tmp.npz")
        np.savez_compressed(
            tmp,
            first=self.first,
            last=self.last,
            instructions=np.array(self.instructions),
            tasks=np.array(self.tasks),
        )
        os.replace(tmp, path)

    @classmethod
    def load(cls, path: str | Path) -> FramePairs:
        with np.load(path) as z:
            return cls(
                z["first"],
                z["last"],
                [str(s) for s in z["instructions"]],
                [str(s) for s in z["tasks"]],
            )


_REQUIRED = object()


def _get(record: Any, *names: str, default: Any = _REQUIRED) -> Any:
    for name in names:
        if isinstance(record, Mapping) and name in record:
            return record[name]
        if not isinstance(record, Mapping) and hasattr(record, name):
            return getattr(record, name)
    if default is _REQUIRED:
        raise KeyError(f"record has none of {names}: {type(record).__name__}")
    return default


# ---- synthetic stand-in ----

_COLOURS = {
    "red": (220, 40, 40),
    "green": (40, 190, 60),
    "blue": (50, 80, 230),
    "yellow": (230, 210, 40),
}
_MOVES = {"left": (0, -1), "right": (0, 1), "up": (-1, 0), "down": (1, 0)}
_VERBS = ("push", "slide", "move")


def synthetic(n: int, seed: int = 0) -> FramePairs:
    """n demos on a grey table: a target square and a distractor; the instruction
    ("push the red block left") names the target's colour and where it ends up.
    Task = the direction, so same-task retrieval has a right answer."""
    rng = np.random.default_rng(seed)
    colours, moves = list(_COLOURS), list(_MOVES)
    first = np.empty((n, FRAME_SIZE, FRAME_SIZE, 3), np.uint8)
    last = np.empty_like(first)
    instructions, tasks = [], []
    size, shift = 20, 40
    for i in range(n):
        target, other = rng.choice(len(colours), 2, replace=False)
        move = moves[rng.integers(len(moves))]
        dy, dx = _MOVES[move]
        lo, hi = shift, FRAME_SIZE - shift - size
        pos = rng.integers(lo, hi + 1, 2)
        other_pos = rng.integers(0, FRAME_SIZE - size, 2)
        for frame, p in ((first[i], pos), (last[i], pos + shift * np.array([dy, dx]))):
            frame[:] = 120
            _square(frame, other_pos, size, _COLOURS[colours[other]])
            _square(frame, p, size, _COLOURS[colours[target]])
        instructions.append(
            f"{_VERBS[rng.integers(len(_VERBS))]} the {colours[target]} block {move}"
        )
        tasks.append(f"move_{move}")
    return FramePairs(first, last, instructions, tasks)


def _square(frame: np.ndarray, pos: np.ndarray, size: int, colour: tuple[int, int, int]) -> None:
    y, x = int(pos[0]), int(pos[1])
    frame[y : y + size, x : x + size] = colour
