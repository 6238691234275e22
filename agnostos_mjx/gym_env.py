"""The gymnasium VectorEnv behind the LeRobot plug-in (lerobot_env_agnostos/), by the name
its users import: the env is agnostos_mjx/gym/env.py (its docstring says how it runs), its
options, spaces and policy checks agnostos_mjx/gym/options.py."""

from agnostos_mjx.gym.env import (
    KNOWN_OPTIONS,
    SUITES,
    AgnostosVectorEnv,
    make_suites,
    resolve_tasks,
)
from agnostos_mjx.gym.options import (
    AUTORESET_MODES,
    CONTROL_MODES,
    FROM_POLICY,
    LAYOUT_OPTIONS,
    ROTATION_BOUNDS,
    STATE_KEY,
    EnvOptions,
    dataset_inputs,
    lerobot_features,
    look_warning,
    options_for_policy,
    render_route,
    single_spaces,
)

__all__ = ["AUTORESET_MODES", "CONTROL_MODES", "FROM_POLICY", "KNOWN_OPTIONS",
           "LAYOUT_OPTIONS", "ROTATION_BOUNDS", "STATE_KEY", "SUITES", "AgnostosVectorEnv",
           "EnvOptions", "dataset_inputs", "lerobot_features", "look_warning", "make_suites",
           "options_for_policy", "render_route", "resolve_tasks", "single_spaces"]
