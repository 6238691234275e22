"""The seen-task demonstration bank on disk, and the API to read it.

Layout of a bank directory::

    manifest.json        format version, package version, generation config,
                         per task: file name, SHA-256, demo count, failures
    <task>.npz           one compressed archive per task (no pickles)

Each `<task>.npz` holds N demonstrations as arrays (K = MAX_KEYS key-action slots,
O named objects, T_i trajectory frames at 20 Hz, RLBench's observation rate)::

    index (N,)  variation (N,)  attempt (N,)  sim_steps (N,)  n_keys (N,)
    instruction (N,) str        descriptions (N,) str (JSON list)
    object_names (O,) str       objects (N, O, 3)  world centres at the first frame
    keyframes (N, K)            frame index of each key action (-1 = padding)
    key_pos (N, K, 3)  key_quat (N, K, 4, wxyz)  key_open (N, K)  key_ints (N, K, 7)
    traj (sum T_i, 8)           tip position, quaternion and gripper-open flag
    traj_offsets (N + 1,)       demo i's frames are traj[off[i]:off[i + 1]]
    rgb_<camera>_first / rgb_<camera>_last (N, H, W, 3) uint8
    meta () str (JSON)          task, split, cameras, image size, format version

Writes are atomic (temporary file + rename); the manifest is written after
the archive it describes.  Reading verifies the checksum, so a truncated or
modified file is reported by name instead of producing wrong demos.
"""

from __future__ import annotations

import hashlib
import io
import json
import zipfile
import zlib
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from agnostos_mjx.infra.cli import atomic_write
from agnostos_mjx.sim.textualise import format_demo, point_to_voxel

FORMAT_VERSION = 1
MANIFEST = "manifest.json"
MAX_KEYS = 64  # storage slots; long demos (stack_blocks) exceed X-ICM's 25-step episodes
TRAJ_FIELDS = ("x", "y", "z", "qw", "qx", "qy", "qz", "gripper_open")
REQUIRED_ARRAYS = frozenset({"index", "meta", "n_keys", "traj", "traj_offsets", "instruction"})


class BankError(Exception):
    """A missing, corrupt or mismatched bank file; the message names the file."""


@dataclass(frozen=True)
class Demo:
    """One expert demonstration, as X-ICM uses it."""

    task: str
    index: int
    variation: int
    seed: int
    instruction: str
    descriptions: tuple[str, ...]
    objects: dict[str, np.ndarray]  # name -> world centre (3,) at the first frame
    keyframes: np.ndarray  # (n,) trajectory frame of each key action
    key_pos: np.ndarray  # (n, 3)
    key_quat: np.ndarray  # (n, 4) wxyz
    key_open: np.ndarray  # (n,) 1 = open
    key_ints: np.ndarray  # (n, 7) X-ICM integers
    trajectory: np.ndarray  # (T, 8), see TRAJ_FIELDS
    sim_steps: int
    frames: dict[str, tuple[np.ndarray, np.ndarray]] = field(repr=False, default_factory=dict)

    def object_voxels(self) -> dict[str, list[int]]:
        return {n: [int(v) for v in np.asarray(point_to_voxel(p))] for n, p in self.objects.items()}

    def text(self) -> str:
        """The in-context segment X-ICM puts in its prompt for this demo."""
        return format_demo(self.instruction, self.object_voxels(), self.key_ints)


def sha256(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


def write_shard(path: Path, arrays: dict[str, np.ndarray]) -> str:
    """Atomically write one task archive; returns its SHA-256."""
    buf = io.BytesIO()
    np.savez_compressed(buf, **arrays)
    data = buf.getvalue()
    atomic_write(path, data)
    return hashlib.sha256(data).hexdigest()


def read_shard(path: Path, expected_sha: str | None = None) -> dict[str, np.ndarray]:
    """Load a task archive fully; BankError naming the file if it is unusable."""
    if not path.exists():
        raise BankError(f"{path}: missing (listed in the manifest)")
    if expected_sha is not None and sha256(path) != expected_sha:
        raise BankError(f"{path}: checksum mismatch, the file is corrupt or was modified; "
                        "delete it and rerun the generator with the same --out to rebuild it")
    if not zipfile.is_zipfile(path):  # np.load would try it as a pickle or a .npy
        raise BankError(f"{path}: not an .npz (zip) archive; delete it and rerun the "
                        "generator with the same --out to rebuild it")
    try:
        with np.load(path, allow_pickle=False) as z:
            arrays = {k: z[k] for k in z.files}
        meta = json.loads(str(arrays.get("meta", "{}")))
    except (zipfile.BadZipFile, zlib.error, ValueError, OSError, EOFError, KeyError) as err:
        raise BankError(f"{path}: unreadable archive ({type(err).__name__}: {err}); delete "
                        "it and rerun the generator with the same --out to rebuild it") from err
    missing = sorted(REQUIRED_ARRAYS - set(arrays))
    if missing:
        raise BankError(f"{path}: not a bank archive (no {', '.join(missing)})")
    if meta.get("format_version") != FORMAT_VERSION:
        raise BankError(f"{path}: format version {meta.get('format_version')!r}, "
                        f"this package reads version {FORMAT_VERSION}")
    return arrays


def read_manifest(root: Path) -> dict:
    path = Path(root) / MANIFEST
    if not path.exists():
        raise BankError(f"{root}: not a demonstration bank (no {MANIFEST}); create one with "
                        f"python -m agnostos_mjx.data.generate --out {root}")
    try:
        manifest = json.loads(path.read_text(encoding="utf-8"))
    except (json.JSONDecodeError, UnicodeDecodeError) as err:
        raise BankError(f"{path}: not valid JSON ({err})") from err
    if not isinstance(manifest, dict) or manifest.get("format_version") != FORMAT_VERSION:
        version = manifest.get("format_version") if isinstance(manifest, dict) else None
        raise BankError(f"{path}: format version {version!r}, this "
                        f"package reads version {FORMAT_VERSION}; regenerate the bank")
    tasks = manifest.get("tasks")
    if not isinstance(tasks, dict) or not isinstance(manifest.get("config"), dict) or any(
            not isinstance(e, dict) or not {"file", "demos"} <= set(e) for e in tasks.values()):
        raise BankError(f"{path}: incomplete manifest (needs config and, per task, file and "
                        "demos); regenerate the bank")
    return manifest


def write_manifest(root: Path, manifest: dict) -> None:
    atomic_write(Path(root) / MANIFEST, json.dumps(manifest, indent=1, sort_keys=True) + "\n")


class DemoBank:
    """Read access to a bank directory.  Archives load (and are verified) on
    first use and stay cached."""

    def __init__(self, root: str | Path):
        self.root = Path(root)
        self.manifest = read_manifest(self.root)
        self._cache: dict[str, dict[str, np.ndarray]] = {}

    @property
    def tasks(self) -> list[str]:
        return [t for t, e in self.manifest["tasks"].items() if e["demos"] > 0]

    @property
    def cameras(self) -> list[str]:
        return list(self.manifest["config"]["cameras"])

    def __len__(self) -> int:
        return sum(e["demos"] for e in self.manifest["tasks"].values())

    def arrays(self, task: str) -> dict[str, np.ndarray]:
        """All arrays of one task (see the module docstring)."""
        if task not in self._cache:
            entry = self.manifest["tasks"].get(task)
            if entry is None:
                raise BankError(f"{self.root}: no demos of task {task!r}; "
                                f"the bank has {', '.join(self.tasks)}")
            arrays = read_shard(self.root / entry["file"], entry.get("sha256"))
            if len(arrays["index"]) != entry["demos"]:
                raise BankError(f"{self.root / entry['file']}: {len(arrays['index'])} demos, "
                                f"the manifest says {entry['demos']}")
            self._cache[task] = arrays
        return self._cache[task]

    def demo(self, task: str, i: int) -> Demo:
        """Demo number `i` (0-based position in the task's archive)."""
        a = self.arrays(task)
        if not 0 <= i < len(a["index"]):
            raise IndexError(f"{task} has demos 0..{len(a['index']) - 1}, asked for {i}")
        n = int(a["n_keys"][i])
        off = a["traj_offsets"]
        names = [str(s) for s in a["object_names"]]
        frames = {c: (a[f"rgb_{c}_first"][i], a[f"rgb_{c}_last"][i])
                  for c in json.loads(str(a["meta"]))["cameras"]}
        return Demo(
            task=task, index=int(a["index"][i]), variation=int(a["variation"][i]),
            seed=int(self.manifest["config"]["seed"]), instruction=str(a["instruction"][i]),
            descriptions=tuple(json.loads(str(a["descriptions"][i]))),
            objects={nm: a["objects"][i, k] for k, nm in enumerate(names)},
            keyframes=a["keyframes"][i, :n], key_pos=a["key_pos"][i, :n],
            key_quat=a["key_quat"][i, :n], key_open=a["key_open"][i, :n],
            key_ints=a["key_ints"][i, :n], trajectory=a["traj"][off[i]:off[i + 1]],
            sim_steps=int(a["sim_steps"][i]), frames=frames,
        )

    def demos(self, task: str | None = None) -> Iterator[Demo]:
        for t in [task] if task else self.tasks:
            for i in range(len(self.arrays(t)["index"])):
                yield self.demo(t, i)

    def frame_pairs(self, camera: str = "front"):
        """(first frames, last frames, instructions, task names) over the whole
        bank, in task then demo order: the dynamics model's training data."""
        if camera not in self.cameras:
            raise BankError(f"{self.root}: camera {camera!r} not stored; has {self.cameras}")
        first, last, instructions, tasks = [], [], [], []
        for t in self.tasks:
            a = self.arrays(t)
            first.append(a[f"rgb_{camera}_first"])
            last.append(a[f"rgb_{camera}_last"])
            instructions += [str(s) for s in a["instruction"]]
            tasks += [t] * len(a["index"])
        return np.concatenate(first), np.concatenate(last), instructions, tasks
