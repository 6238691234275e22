"""The seen-demo memory X-ICM selects its in-context examples from.

Per demonstration: task, variation, instruction, its prompt segment (object
text + key actions, exactly as X-ICM writes it), the continuous key actions
and object centres (for the retrieval baseline), and optional selection
features (``lang``, ``vis.in``, ``vis.out``) from the dynamics model.  It is
built once from a demonstration bank and saved as one compressed .npz that
ships with the package, so evaluation needs neither the bank nor training.
"""

from __future__ import annotations

import io
import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from agnostos_mjx.data.bank import MAX_KEYS
from agnostos_mjx.infra.cli import atomic_write

MEMORY_VERSION = 2  # 2: features stored deduplicated and int8-quantised (see _pack_feature)
MAX_OBJECTS = 8


class MemoryFileError(Exception):
    """A missing or incompatible memory file."""


@dataclass(frozen=True, eq=False)
class DemoMemory:
    task: np.ndarray  # (M,) str
    variation: np.ndarray  # (M,) int
    instruction: np.ndarray  # (M,) str
    text: np.ndarray  # (M,) str, the demo's prompt segment (ends with ", ")
    n_keys: np.ndarray  # (M,)
    key_pos: np.ndarray  # (M, MAX_KEYS, 3)
    key_quat: np.ndarray  # (M, MAX_KEYS, 4)
    key_open: np.ndarray  # (M, MAX_KEYS)
    object_names: np.ndarray  # (M,) str, JSON list per demo
    objects: np.ndarray  # (M, MAX_OBJECTS, 3), NaN padded
    features: dict[str, np.ndarray] = field(default_factory=dict)  # name -> (M, D)

    def __len__(self) -> int:
        return len(self.task)

    def names(self, i: int) -> list[str]:
        return json.loads(str(self.object_names[i]))

    @classmethod
    def from_bank(cls, bank, features: dict[str, np.ndarray] | None = None) -> DemoMemory:
        rows: dict[str, list] = {k: [] for k in (
            "task", "variation", "instruction", "text", "n_keys", "key_pos", "key_quat",
            "key_open", "object_names", "objects")}
        for demo in bank.demos():
            n = len(demo.key_ints)
            pad = lambda a, width=MAX_KEYS: np.concatenate(  # noqa: E731
                [a, np.zeros((width - len(a), *a.shape[1:]), a.dtype)])
            objs = np.full((MAX_OBJECTS, 3), np.nan, np.float32)
            names = list(demo.objects)[:MAX_OBJECTS]
            for k, name in enumerate(names):
                objs[k] = demo.objects[name]
            rows["task"].append(demo.task)
            rows["variation"].append(demo.variation)
            rows["instruction"].append(demo.instruction)
            rows["text"].append(demo.text())
            rows["n_keys"].append(n)
            rows["key_pos"].append(pad(demo.key_pos.astype(np.float32)))
            rows["key_quat"].append(pad(demo.key_quat.astype(np.float32)))
            rows["key_open"].append(pad(demo.key_open.astype(np.float32)))
            rows["object_names"].append(json.dumps(names))
            rows["objects"].append(objs)
        arrays = {k: np.asarray(v) for k, v in rows.items()}
        return cls(**arrays, features=dict(features or {}))

    @classmethod
    def concat(cls, *memories: DemoMemory) -> DemoMemory:
        """One memory from several (e.g. an existing memory and a bank of new tasks);
        features are kept only where every part has them."""
        names = [k for k in cls.__dataclass_fields__ if k != "features"]
        arrays = {k: np.concatenate([getattr(m, k) for m in memories]) for k in names}
        common = set.intersection(*(set(m.features) for m in memories))
        features = {k: np.concatenate([m.features[k] for m in memories]) for k in sorted(common)}
        return cls(**arrays, features=features)

    def without_tasks(self, tasks: set[str]) -> DemoMemory:
        """This memory less the demos of `tasks` (e.g. before re-adding re-recorded ones)."""
        keep = ~np.isin(self.task, sorted(tasks))
        names = [k for k in self.__dataclass_fields__ if k != "features"]
        return type(self)(**{k: getattr(self, k)[keep] for k in names},
                          features={k: v[keep] for k, v in self.features.items()})

    def save(self, path: str | Path) -> None:
        arrays = {k: getattr(self, k) for k in self.__dataclass_fields__ if k != "features"}
        for name, values in self.features.items():
            arrays.update({f"feature:{name}:{part}": a
                           for part, a in _pack_feature(values).items()})
        arrays["version"] = np.asarray(MEMORY_VERSION)
        buf = io.BytesIO()
        np.savez_compressed(buf, **arrays)
        atomic_write(Path(path), buf.getvalue())

    @classmethod
    def load(cls, path: str | Path) -> DemoMemory:
        path = Path(path)
        if not path.exists():
            raise MemoryFileError(f"{path}: no demo memory; build one with "
                               "python -m agnostos_mjx.xicm.build_memory")
        try:
            with np.load(path, allow_pickle=False) as z:
                arrays = {k: z[k] for k in z.files}
        except Exception as err:  # a damaged zip raises several types
            raise MemoryFileError(f"{path}: unreadable ({type(err).__name__}: {err})") from err
        if int(arrays.pop("version", -1)) != MEMORY_VERSION:
            raise MemoryFileError(f"{path}: memory version mismatch; rebuild it")
        packed: dict[str, dict[str, np.ndarray]] = {}
        for key in [k for k in arrays if k.startswith("feature:")]:
            _, name, part = key.split(":")
            packed.setdefault(name, {})[part] = arrays.pop(key)
        try:
            features = {name: _unpack_feature(parts) for name, parts in packed.items()}
            return cls(**arrays, features=features)
        except (KeyError, TypeError, ValueError, IndexError) as err:
            raise MemoryFileError(f"{path}: malformed memory ({err}); rebuild it") from err


def _pack_feature(values: np.ndarray) -> dict[str, np.ndarray]:
    """Unique rows as int8 codes with one float32 scale per row, plus each demo's row.

    Why: the shipped memory must stay small (issue 6 budget: export + memory < 40 MB).
    ``lang`` depends only on the instruction (249 distinct among 3,600 demos) and the
    int8 codes keep cosine similarity within ~1e-4 of float32, which leaves rankings intact
    (tests/test_xicm.py checks it)."""
    unique, rows = np.unique(np.asarray(values, np.float32), axis=0, return_inverse=True)
    scale = np.abs(unique).max(axis=1) / 127.0
    scale = np.where(scale > 0, scale, 1.0).astype(np.float32)
    codes = np.clip(np.rint(unique / scale[:, None]), -127, 127).astype(np.int8)
    return {"codes": codes, "scale": scale, "rows": rows.reshape(-1).astype(np.int32)}


def _unpack_feature(parts: dict[str, np.ndarray]) -> np.ndarray:
    table = parts["codes"].astype(np.float32) * parts["scale"][:, None].astype(np.float32)
    return table[parts["rows"]]


def default_memory_path() -> Path:
    """The memory shipped with the package (built from the default seen bank)."""
    return Path(__file__).resolve().parents[1] / "assets" / "seen_memory.npz"
