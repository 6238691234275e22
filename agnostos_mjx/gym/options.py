"""The gymnasium env's options and what they make of its rows (the env: gym/env.py):
``EnvOptions`` (the LeRobot export's layout flags and how episodes run), one world's
spaces, the LeRobot features they map to, and how they fit a policy: its feature shapes
and names (``options_for_policy``) and the look of its training data (``look_warning``).
Apart from the env class so that the plug-in's config reads them without building one."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import gymnasium as gym
import numpy as np
from gymnasium.vector import AutoresetMode

from agnostos_mjx.data.lerobot_layout import (
    IMAGE_PREFIX,
    STATE_NAMES,
    action_names,
    check_state,
)
from agnostos_mjx.data.rotations import ROTATION_NAMES, check_rotation
from agnostos_mjx.evaluation.config import VARIATION_MODES
from agnostos_mjx.physics import RENDERERS
from agnostos_mjx.runtime.observation import CAMERAS
from agnostos_mjx.sim.control import ACTION_BOUNDS

CONTROL_MODES = ("keyaction", "dense")
AUTORESET_MODES = {"next_step": AutoresetMode.NEXT_STEP, "same_step": AutoresetMode.SAME_STEP}
# Each rotation's value range (the action space's bounds; the planner judges the rest).
ROTATION_BOUNDS = {"quat": 1.0, "euler": np.pi, "axis_angle": np.pi, "rot6d": 1.0}
STATE_KEY = "observation.state"  # the export's (and LeRobot's) state feature


@dataclass(frozen=True)
class EnvOptions:
    """How the env's rows look and run; the layout flags are the LeRobot export's (its
    defaults: RLBench's five cameras at 224 px, rlbench state, quaternion actions)."""

    cameras: tuple[str, ...] = CAMERAS
    size: int = 224
    state: str = "rlbench"
    rotation: str = "quat"
    control_mode: str = "keyaction"
    control_hz: float = 20.0  # dense: control steps per second
    dense_steps: int | None = None  # dense: the step budget (default: runtime/dense.py's)
    backend: str = "native"
    variations: str = "protocol"  # as the evaluator's --variations (protocol|all|zero|N)
    protocol_seed: int = 0
    render_camera: str = "front"
    render_size: int | None = None  # default: size
    autoreset_mode: str = "next_step"
    renderer: str = "auto"  # as the evaluator's --renderer (physics.RENDERERS)

    def __post_init__(self) -> None:
        names = self.cameras.split(",") if isinstance(self.cameras, str) else self.cameras
        cams = tuple(c.strip() for c in names if c.strip())  # "front,wrist" from a CLI too
        object.__setattr__(self, "cameras", cams)
        bad = [c for c in cams if c not in CAMERAS]
        if bad or not cams or len(set(cams)) != len(cams):
            raise ValueError(f"cameras must be distinct names among {', '.join(CAMERAS)}; "
                             f"got {','.join(cams) or 'none'}")
        if self.render_camera not in CAMERAS:
            raise ValueError(f"render_camera must be one of {', '.join(CAMERAS)}, "
                             f"got {self.render_camera!r}")
        for name in ("size", "render_size"):
            value = getattr(self, name)
            if value is not None and (not isinstance(value, int) or value < 1):
                raise ValueError(f"{name} must be a positive number of pixels, got {value!r}")
        check_state(self.state)
        check_rotation(self.rotation)
        if self.control_mode not in CONTROL_MODES:
            raise ValueError(f"unknown control_mode {self.control_mode!r}; choose from "
                             f"{', '.join(CONTROL_MODES)}")
        if not isinstance(self.control_hz, (int, float)) or not self.control_hz > 0:
            raise ValueError(f"control_hz must be a positive rate, got {self.control_hz!r}")
        if self.dense_steps is not None and (not isinstance(self.dense_steps, int)
                                             or self.dense_steps < 1):
            raise ValueError(f"dense_steps must be a positive integer, got "
                             f"{self.dense_steps!r}")
        if self.autoreset_mode not in AUTORESET_MODES:
            raise ValueError(f"unknown autoreset_mode {self.autoreset_mode!r}; choose from "
                             f"{', '.join(AUTORESET_MODES)}")
        if self.variations not in VARIATION_MODES and not self.variations.isdigit():
            raise ValueError(f"variations must be one of {', '.join(VARIATION_MODES)} or a "
                             f"variation number, got {self.variations!r}")
        if not isinstance(self.protocol_seed, int) or self.protocol_seed < 0:
            raise ValueError(f"protocol_seed must be an integer >= 0, got {self.protocol_seed!r}")
        if self.renderer not in RENDERERS:
            raise ValueError(f"unknown renderer {self.renderer!r}; choose from "
                             f"{', '.join(RENDERERS)}")

    @property
    def action_dim(self) -> int:
        return len(action_names(self.rotation))

    @property
    def state_dim(self) -> int:
        return len(STATE_NAMES[self.state])


def lerobot_features(opts: EnvOptions) -> dict[str, tuple[str, tuple[int, ...], str]]:
    """Per raw env key: (LeRobot feature type ACTION / STATE / VISUAL, shape, the policy
    key LeRobot maps it to): the plug-in's ``features`` and ``features_map``, so the
    policy sees the export's keys."""
    out = {"action": ("ACTION", (opts.action_dim,), "action"),
           "agent_pos": ("STATE", (opts.state_dim,), STATE_KEY)}
    for cam in opts.cameras:
        out[f"pixels/{cam}"] = ("VISUAL", (opts.size, opts.size, 3), IMAGE_PREFIX + cam)
    return out


def dataset_inputs(features: Mapping[str, Mapping[str, Any]]
                   ) -> tuple[dict[str, tuple[int, ...]], dict[str, tuple[str, ...]]]:
    """A LeRobot dataset's features (its meta/info.json ``features``) as a policy trained on
    it sees them: the shapes of its ``observation.*`` and ``action`` features (images
    channel-first, as LeRobot's ``dataset_to_policy_features`` turns them), and the
    per-dimension names of ``observation.state`` and ``action``, which name the export's
    state and rotation layouts (data/lerobot_layout.py)."""
    shapes: dict[str, tuple[int, ...]] = {}
    names: dict[str, tuple[str, ...]] = {}
    for key, ft in features.items():
        if not key.startswith(("observation", "action")):
            continue
        shape = tuple(int(n) for n in ft["shape"])
        if ft.get("dtype") in ("image", "video") and len(shape) == 3 and \
                list(ft.get("names") or [])[2:3] in (["channel"], ["channels"]):
            shape = (shape[2], shape[0], shape[1])
        shapes[key] = shape
        if key in (STATE_KEY, "action") and isinstance(ft.get("names"), list):
            names[key] = tuple(ft["names"])
    return shapes, names


# The layouts a policy's state and action names can name: the option that picks each.
LAYOUT_OPTIONS = {STATE_KEY: ("state", STATE_NAMES),
                  "action": ("rotation", {r: action_names(r) for r in ROTATION_NAMES})}
# Options that the policy's features (shapes, names) fill in when left unset (None).
FROM_POLICY = ("cameras", "size", "state", "rotation")


def options_for_policy(features: Mapping[str, Sequence[int]] | None,
                       names: Mapping[str, Sequence[str]] | None = None,
                       **options: Any) -> EnvOptions:
    """EnvOptions that give a LeRobot policy the inputs it was trained on.

    `features`: the policy's feature shapes, inputs and ``action`` (LeRobot's
    ``input_features`` and ``output_features``, or ``dataset_inputs`` of its training
    data), or None for no policy.  `names`: the training data's names of the
    ``observation.state`` and ``action`` dimensions (``dataset_inputs``), when known.
    ``cameras`` and ``size`` left out (or None) come from its ``observation.images.<camera>``
    inputs, shape (3, N, N), ``state`` and ``rotation`` from the layouts its names name;
    given ones are checked against them, and against its ``observation.state`` and
    ``action`` sizes.  A policy fed other inputs than it was trained on still runs and
    scores 0% without a word (the rlbench and libero states are both 8 long: only the
    names tell them apart), so any feature the env cannot give is a ValueError, in one
    line, that names it."""
    images: dict[str, int] = {}
    problems: list[str] = []
    names = {key: tuple(n) for key, n in (names or {}).items()}
    given = [k for k in FROM_POLICY if options.get(k) is not None]
    for key, shape in (features or {}).items():
        shape = tuple(int(s) for s in shape)
        camera = key.removeprefix(IMAGE_PREFIX)
        if key in (STATE_KEY, "action"):
            continue
        if camera == key:
            problems.append(f"{key} {shape} (the env gives {IMAGE_PREFIX}<camera> and "
                            f"{STATE_KEY})")
        elif camera not in CAMERAS:
            problems.append(f"{key} (no such camera; ours: {', '.join(CAMERAS)})")
        elif len(shape) != 3 or shape[0] != 3 or shape[1] != shape[2]:
            problems.append(f"{key} {shape} (the env renders RGB squares, (3, N, N))")
        else:
            images[camera] = shape[1]
    if "cameras" not in given and images:
        options["cameras"] = tuple(images)
    if "size" not in given and images:
        options["size"] = max(images.values())  # unequal sizes are reported below
    named = {}  # per named feature: the layout its names name, or None
    for key, (option, layouts) in LAYOUT_OPTIONS.items():
        if key in names:
            named[key] = next((lay for lay, n in layouts.items() if n == names[key]), None)
            if option not in given and named[key] is not None:
                options[option] = named[key]
    opts = EnvOptions(**{k: v for k, v in options.items()
                         if v is not None or k not in FROM_POLICY})
    problems += [f"{IMAGE_PREFIX}{cam} (3, {n}, {n})" for cam, n in images.items()
                 if cam not in opts.cameras or n != opts.size]
    wants = {STATE_KEY: (opts.state_dim,), "action": (opts.action_dim,)}
    for key, shape in wants.items():
        if key in (features or {}) and tuple(features[key]) != shape:
            problems.append(f"{key} {tuple(features[key])}")
    ours = {STATE_KEY: STATE_NAMES[opts.state], "action": action_names(opts.rotation)}
    for key, layout in named.items():
        if names[key] != ours[key]:
            what = f"{LAYOUT_OPTIONS[key][0]} {layout}" if layout else "no layout of ours"
            problems.append(f"{key} named {','.join(names[key])} ({what})")
    if problems:
        hint = f"; leave {' and '.join(given)} unset to take the policy's" if given else ""
        raise ValueError(
            f"the policy wants what this env does not give: {'; '.join(problems)} (the env "
            f"gives cameras {','.join(opts.cameras)} at {opts.size} px, {STATE_KEY} "
            f"({opts.state_dim},) for state {opts.state}, action ({opts.action_dim},) for "
            f"rotation {opts.rotation}){hint}")
    return opts


def single_spaces(opts: EnvOptions) -> tuple[gym.spaces.Dict, gym.spaces.Box]:
    """One world's observation space (the export's images and state) and action space (its
    action row: the workspace, the rotation's range, the gripper's [0, 1])."""
    pixels = gym.spaces.Dict({c: gym.spaces.Box(0, 255, (opts.size, opts.size, 3), np.uint8)
                              for c in opts.cameras})
    observation = gym.spaces.Dict({
        "pixels": pixels,
        "agent_pos": gym.spaces.Box(-np.inf, np.inf, (opts.state_dim,), np.float32)})
    rot = ROTATION_BOUNDS[opts.rotation]
    nrot = opts.action_dim - 4
    low = np.array([*ACTION_BOUNDS[0], *[-rot] * nrot, 0.0], np.float32)
    high = np.array([*ACTION_BOUNDS[1], *[rot] * nrot, 1.0], np.float32)
    return observation, gym.spaces.Box(low, high, dtype=np.float32)


def render_route(opts: EnvOptions) -> str:
    """"cpu" or "warp": what the env's images render with on this machine (its
    ``renderer``, auto resolved as the evaluator resolves it).  Sets JAX up first, as the
    env does: this may be the process's first use of JAX."""
    from agnostos_mjx.infra.settings import configure_jax
    from agnostos_mjx.physics import resolve_renderer

    if opts.renderer == "auto":
        configure_jax()
    return resolve_renderer(opts.renderer, opts.backend)


def look_warning(dataset_meta: Mapping[str, Any] | None, opts: EnvOptions,
                 renderer_flag: str = "renderer") -> str | None:
    """One line when the training data (its meta/info.json as a dict) was rendered by
    another renderer or scene version than this env renders with (data/look.py's
    check_look), naming the `renderer_flag` that renders as the data did; None when they agree
    or the data records none."""
    from agnostos_mjx.data.look import LOOK_KEY, check_look

    record = (dataset_meta or {}).get(LOOK_KEY)
    if not isinstance(record, Mapping):
        return None  # no record: nothing to compare (and no need to resolve the route)
    route = render_route(opts)
    text = check_look(dataset_meta, route)
    if text and record.get("renderer") in RENDERERS and record["renderer"] != route:
        text += f"; {renderer_flag}={record['renderer']} renders as the data was"
    return text

