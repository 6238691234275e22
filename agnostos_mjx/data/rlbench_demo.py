"""RLBench's episode pickles without rlbench installed: ``low_dim_obs.pkl``, and the
restricted reading of all three (``variation_descriptions.pkl``, ``variation_number.pkl``).

RLBench's dataset generator pickles an ``rlbench.demo.Demo`` whose ``_observations`` are
``rlbench.backend.observation.Observation`` objects with the images set to None (they are
PNGs beside the pickle); ``rlbench.utils.get_stored_demos`` (PerAct, RVT) unpickles it.
Pickle names classes by module path, so :class:`Demo` and :class:`Observation` here are
stand-ins that :func:`dumps` writes under RLBench's paths (``rlbench.demo`` /
``rlbench.backend.observation``) and :func:`loads` maps back; a real rlbench install reads
the same bytes as its own classes.  Arrays are written under ``numpy.core.multiarray``
(numpy 1.x's path, which numpy 2 still reads) rather than numpy 2's ``numpy._core``, which
the numpy 1 environments of PerAct and RVT cannot import.

Field set and types follow a pickle written by RLBench itself (PerAct's fork, as in
``peract_colab``'s sample data): float64 arrays, ``gripper_open`` a Python float,
``ignore_collisions`` a 0-d float64 array, ``misc`` with ``<camera>_camera_extrinsics``
(4, 4), ``_intrinsics`` (3, 3), ``_near`` and ``_far`` (floats) per camera.

Reading is restricted (:func:`read_pickle`): an exported episode may come from elsewhere,
and a plain ``pickle.load`` runs whatever callable a pickle names.  Each file may name only
the globals its content needs - RLBench's two classes and numpy's array reconstruction for
``low_dim_obs.pkl``; for the variation number a numpy scalar at most; nothing at all for the
descriptions (a list of str) - and anything else is refused with an UnpicklingError naming
the file and the global.
"""

from __future__ import annotations

import io
import pickle
from pathlib import Path
from typing import Any

import numpy as np

# rlbench.backend.observation.Observation's constructor fields (PerAct's RLBench fork, read
# by PerAct and RVT; upstream RLBench has the same minus ignore_collisions).
OBSERVATION_FIELDS = (
    "left_shoulder_rgb", "left_shoulder_depth", "left_shoulder_mask",
    "left_shoulder_point_cloud", "right_shoulder_rgb", "right_shoulder_depth",
    "right_shoulder_mask", "right_shoulder_point_cloud", "overhead_rgb", "overhead_depth",
    "overhead_mask", "overhead_point_cloud", "wrist_rgb", "wrist_depth", "wrist_mask",
    "wrist_point_cloud", "front_rgb", "front_depth", "front_mask", "front_point_cloud",
    "joint_velocities", "joint_positions", "joint_forces", "gripper_open", "gripper_pose",
    "gripper_matrix", "gripper_joint_positions", "gripper_touch_forces",
    "task_low_dim_state", "ignore_collisions", "misc",
)
PROTOCOL = 4  # what RLBench's pickles use (Python 3 default when they were written)
LOW_DIM_PICKLE = "low_dim_obs.pkl"
DESCRIPTIONS_PICKLE = "variation_descriptions.pkl"  # list of str
NUMBER_PICKLE = "variation_number.pkl"  # int


class Observation:
    """Stand-in for ``rlbench.backend.observation.Observation`` (fields only)."""

    def __init__(self, **fields: Any):
        unknown = set(fields) - set(OBSERVATION_FIELDS)
        if unknown:
            raise TypeError(f"not RLBench Observation fields: {sorted(unknown)}")
        for name in OBSERVATION_FIELDS:
            setattr(self, name, fields.get(name))


class Demo:
    """Stand-in for ``rlbench.demo.Demo`` (attributes as PerAct's RLBench fork pickles
    them: ``_observations``, ``random_seed``, ``variation_number``)."""

    def __init__(self, observations: list, random_seed: Any = None, variation_number: int = 0):
        self._observations = observations
        self.random_seed = random_seed
        self.variation_number = variation_number

    def __len__(self) -> int:
        return len(self._observations)

    def __getitem__(self, i: int) -> Observation:
        return self._observations[i]


CLASS_PATHS: dict[type, tuple[str, str]] = {
    Demo: ("rlbench.demo", "Demo"),
    Observation: ("rlbench.backend.observation", "Observation"),
}
_BY_PATH = {path: cls for cls, path in CLASS_PATHS.items()}
_NUMPY_NAMES = {"_reconstruct", "scalar", "ndarray", "dtype"}


def _global_path(obj: Any) -> tuple[str, str] | None:
    if isinstance(obj, type) and obj in CLASS_PATHS:
        return CLASS_PATHS[obj]
    module = getattr(obj, "__module__", None) or ""
    if module == "numpy._core" or module.startswith("numpy._core."):
        return "numpy.core" + module[len("numpy._core"):], obj.__qualname__
    return None


class _Pickler(pickle._Pickler):  # the Python pickler: its save_global can be overridden
    def save_global(self, obj: Any, name: str | None = None) -> None:
        path = _global_path(obj)
        if path is None:
            super().save_global(obj, name)
            return
        self.save(path[0])
        self.save(path[1])
        self.write(pickle.STACK_GLOBAL)
        self.memoize(obj)


def dumps(demo: Demo) -> bytes:
    """Pickle bytes that name RLBench's classes (see the module docs)."""
    out = io.BytesIO()
    _Pickler(out, protocol=PROTOCOL).dump(demo)
    return out.getvalue()


_NUMPY_SCALAR_NAMES = {"scalar", "dtype"}
# The globals each episode pickle may name (beyond none at all).
_ALLOWED = {
    LOW_DIM_PICKLE: (frozenset(_BY_PATH), _NUMPY_NAMES),
    NUMBER_PICKLE: (frozenset(), _NUMPY_SCALAR_NAMES),  # a numpy integer from other writers
    DESCRIPTIONS_PICKLE: (frozenset(), frozenset()),
}


class _Unpickler(pickle.Unpickler):
    """Resolves only the allowed globals: RLBench's classes (to our stand-ins) and numpy's
    array names; everything else (os.system, builtins.eval, ...) is refused."""

    def __init__(self, file: Any, what: str = LOW_DIM_PICKLE) -> None:
        super().__init__(file)
        self.what = what
        self.classes, self.numpy_names = _ALLOWED[what]

    def find_class(self, module: str, name: str) -> Any:
        if (module, name) in self.classes:
            return _BY_PATH[(module, name)]
        numpy_module = module == "numpy" or module.startswith(("numpy.core.", "numpy._core."))
        if numpy_module and name in self.numpy_names:
            return super().find_class(module, name)
        place = "an RLBench demo pickle" if self.what == LOW_DIM_PICKLE else self.what
        raise pickle.UnpicklingError(f"{module}.{name} has no place in {place}")


def loads(data: bytes) -> Demo:
    """An RLBench ``low_dim_obs.pkl`` (ours or RLBench's) -> :class:`Demo` of
    :class:`Observation` (only RLBench's two classes and numpy arrays are accepted)."""
    return _Unpickler(io.BytesIO(data)).load()


def read_pickle(path: Path) -> Any:
    """One of an episode's pickles, unpickled with the globals its name allows (module
    docs); UnpicklingError naming `path` for anything else (or for what is not a pickle),
    ValueError naming it if the content is not what RLBench writes there."""
    path = Path(path)
    if path.name not in _ALLOWED:
        raise ValueError(f"{path}: not an RLBench episode pickle ({', '.join(_ALLOWED)})")
    try:
        value = _Unpickler(io.BytesIO(path.read_bytes()), path.name).load()
    except pickle.UnpicklingError as err:
        raise pickle.UnpicklingError(f"refused to unpickle {path}: {err} (episode pickles "
                                     "are read with a restricted unpickler)") from None
    except (EOFError, ValueError, TypeError, IndexError, AttributeError) as err:
        raise pickle.UnpicklingError(f"{path} is not a readable pickle: {err!r}") from None
    if path.name == DESCRIPTIONS_PICKLE and not (
            isinstance(value, list) and all(isinstance(d, str) for d in value)):
        raise ValueError(f"{path}: expected a list of str, got {type(value).__name__}")
    if path.name == NUMBER_PICKLE:
        if isinstance(value, bool) or not isinstance(value, int | np.integer):
            raise ValueError(f"{path}: expected an int, got {type(value).__name__}")
    if path.name == LOW_DIM_PICKLE and not isinstance(value, Demo):
        raise ValueError(f"{path}: expected an RLBench Demo, got {type(value).__name__}")
    return value
