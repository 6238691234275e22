"""What made a dataset's images: the renderer and the scene version.

The export records them under the key ``"agnostos"`` of a LeRobot dataset's
``meta/info.json`` and of an RLBench export's ``manifest.json`` (its root, beside the task
folders; RLBench's readers never open it)::

    "agnostos": {"renderer": "cpu", "scene_version": "1bdc9034a3a9", "package_version": "0.1.0"}

A policy trained on images of one renderer and evaluated on another's sees slightly
different pixels (docs/finetune.md gives the figures); :func:`check_look` says so in one
line, for the LeRobot plug-in and any other consumer.

The scene version (:func:`scene_version`) is a digest of the shared world as compiled
(scenes/world.xml with the Panda): the fields that decide how it looks (geoms' type, size,
colour, material, placement; materials and textures; lights; cameras; the headlight; the
depth clip planes; OpenGL's shadows and tessellation) and RLBench's colour list (colors.py)
that task builders paint objects with.  It is the part every task's images share, so a
dataset of the seen tasks and an evaluation of the unseen ones compare; a task's own
objects are its builder's and are not in it.  Comments and formatting of the XML do not
change it; the package version does not either (recorded beside it, for the reader)."""

from __future__ import annotations

import functools
import hashlib
from collections.abc import Mapping
from pathlib import Path

import numpy as np

from agnostos_mjx.physics.capabilities import RENDER_ROUTES

LOOK_KEY = "agnostos"  # the key of the record in info.json and manifest.json
# The compiled model's fields that decide the look; a field this MuJoCo lacks is skipped.
MODEL_FIELDS = (
    "geom_type", "geom_size", "geom_rgba", "geom_matid", "geom_group", "geom_pos", "geom_quat",
    "body_pos", "body_quat",
    "mat_rgba", "mat_emission", "mat_specular", "mat_shininess", "mat_reflectance",
    "mat_texid", "mat_texrepeat",
    "tex_type", "tex_width", "tex_height", "tex_data",
    "light_active", "light_castshadow", "light_pos", "light_dir", "light_diffuse",
    "light_ambient", "light_specular", "light_attenuation", "light_cutoff", "light_exponent",
    "cam_pos", "cam_quat", "cam_fovy", "cam_mode",
)
VIS_FIELDS = {"headlight": ("active", "ambient", "diffuse", "specular"),
              "map": ("znear", "zfar"),
              "quality": ("shadowsize", "numslices", "numstacks", "numquads")}
DIGITS = 12  # hex digits of the scene version


def _directional(model) -> np.ndarray:
    """Each light's directional flag, whichever way this MuJoCo stores it (light_type
    since 3.3, light_directional before), so the digest does not depend on the name."""
    import mujoco

    if hasattr(model, "light_type"):
        return np.asarray(model.light_type) == int(mujoco.mjtLightType.mjLIGHT_DIRECTIONAL)
    return np.asarray(model.light_directional, bool)


@functools.cache
def scene_version(scenes: Path | None = None) -> str:
    """The digest of the shared world's look (module docstring); `scenes`: the MJCF folder
    (default: world.scenes_dir()).  Values are rounded to 6 decimals, so a MuJoCo that
    stores a field in another float width gives the same digest."""
    import mujoco

    from agnostos_mjx.sim.colors import COLORS
    from agnostos_mjx.sim.world import scenes_dir

    model = mujoco.MjModel.from_xml_path(str(Path(scenes or scenes_dir()) / "world.xml"))
    h = hashlib.sha256()

    def add(name: str, value) -> None:
        a = np.asarray(value)
        a = np.round(a.astype(np.float64), 6) if a.dtype.kind == "f" else a.astype(np.int64)
        h.update(f"{name}:{a.shape};".encode())
        h.update(np.ascontiguousarray(a).tobytes())

    for name in MODEL_FIELDS:
        if hasattr(model, name):
            add(name, getattr(model, name))
    add("light_directional", _directional(model))
    for group, names in VIS_FIELDS.items():
        for name in names:
            add(f"vis.{group}.{name}", getattr(getattr(model.vis, group), name))
    h.update(repr(COLORS).encode())
    return h.hexdigest()[:DIGITS]


def look_record(renderer: str) -> dict[str, str]:
    """The record an export writes under LOOK_KEY for images rendered by `renderer`."""
    from agnostos_mjx import __version__

    _check_route(renderer)
    return {"renderer": renderer, "scene_version": scene_version(),
            "package_version": __version__}


def _check_route(renderer: str) -> None:
    if renderer not in RENDER_ROUTES:
        raise ValueError(f"renderer: the route a run renders with, one of "
                         f"{', '.join(RENDER_ROUTES)} "
                         f"(physics.resolve_renderer), got {renderer!r}")


def check_look(dataset_meta: Mapping, renderer: str) -> str | None:
    """A one-line warning when the dataset whose metadata is `dataset_meta` (a LeRobot
    info.json or an RLBench export's manifest.json, as dicts) was rendered by another
    renderer or scene version than a run rendering with `renderer` ("cpu" or "warp")
    would see; None when they match or the dataset records none (an export made before
    the record, a dataset from elsewhere: nothing to compare)."""
    from agnostos_mjx import __version__

    _check_route(renderer)
    rec = dataset_meta.get(LOOK_KEY)
    if not isinstance(rec, Mapping):
        return None
    now = scene_version()
    diffs = []
    if rec.get("renderer") != renderer:
        diffs.append(f"renderer {rec.get('renderer')} (here {renderer})")
    if rec.get("scene_version") != now:
        diffs.append(f"scene version {rec.get('scene_version')} (here {now})")
    if not diffs:
        return None
    return (f"the training data was rendered with {' and '.join(diffs)}, made by "
            f"agnostos-mjx {rec.get('package_version')} (here {__version__}): the policy "
            f"sees slightly different images than it was trained on")
