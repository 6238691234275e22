"""LeRobot env plug-in ``agnostos``: importing this package registers the env type with
LeRobot when lerobot is installed (LeRobot >= 0.6 imports it itself, as it imports every
installed ``lerobot_env_*`` distribution); without lerobot it still gives the gymnasium
VectorEnv (agnostos_mjx/gym/, the one implementation, imported as agnostos_mjx.gym_env)."""

from __future__ import annotations

import importlib.util

from agnostos_mjx.gym_env import AgnostosVectorEnv, EnvOptions, make_suites, resolve_tasks

__all__ = ["AgnostosVectorEnv", "EnvOptions", "make_suites", "resolve_tasks"]

if importlib.util.find_spec("lerobot") is not None:
    # importing it registers env type 'agnostos' with LeRobot's EnvConfig
    from lerobot_env_agnostos.configuration_agnostos import AgnostosEnvConfig  # noqa: F401

    __all__.append("AgnostosEnvConfig")
