"""The policy plug-in interface: what the evaluator asks of a policy.

A policy drives a batch of B worlds of one task, one key action per world per
step, exactly like an agent in X-ICM's RLBench loop (one key action per
transition).  The evaluator calls

    policy.reset(episodes, env, instructions)   # once per batch, after Episodes.reset
    while not all worlds are done:
        actions = policy.act(episodes, env)     # one KeyActions, leading axis B
        env, _ = episodes.step(env, actions)

`episodes` is the `Episodes` runner (task, scene, expert, renderer hooks) and
`env` the host-side `EnvState` (latest observation, outcome per world, ...).
A world whose action has ``valid=False`` ends with ``Outcome.NO_ACTION``; that
is how a policy says "I have nothing to execute" (an unparsable LLM answer,
an exhausted plan).  Worlds that already finished ignore their action.

A policy that consumes camera images declares an `observation_spec` (an
`agnostos_mjx.observation.ObservationSpec`: cameras, resolution, modalities);
the evaluator then renders exactly that at every step and calls
``policy.act(episodes, env, observation=...)`` with an `RLBenchObservation`
(RGB, depth, point clouds, segmentation, camera matrices, gripper pose and
joints; see observation.py).  Policies without one pay for no rendering.

Policies are found by name with `make_policy`: a registered name ("oracle") or
a "module:attr" / "path/to/file.py:attr" string naming a class, a factory
function or a ready instance.  This is the equivalent of X-ICM's custom-agent
template: write a class with `name`, `reset` and `act`, then run
``python -m agnostos_mjx.eval --policy my_pkg.my_module:MyPolicy``.
"""

from __future__ import annotations

import importlib
import importlib.util
import sys
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, Any, Protocol, runtime_checkable

import numpy as np

from agnostos_mjx.tasks.base import KeyActions

if TYPE_CHECKING:  # the runner imports physics and JAX; keep this module light
    from agnostos_mjx.runtime.env import Episodes
    from agnostos_mjx.runtime.state import EnvState


@runtime_checkable
class Policy(Protocol):
    """One key action per world per step for a batch of episodes of one task."""

    name: str

    def reset(self, episodes: Episodes, env: EnvState, instructions: list[str]) -> None:
        """Start a new batch: `instructions[i]` is world i's language goal."""
        ...

    def act(self, episodes: Episodes, env: EnvState) -> KeyActions:
        """The next key action of every world: pos (B, 3) tip position in world
        coordinates, quat (B, 4) wxyz, gripper (B,) open amount in [0, 1] and
        valid (B,) bool; valid=False ends that world with Outcome.NO_ACTION."""
        ...


def no_actions(batch: int) -> KeyActions:
    """A batch of invalid key actions (every world ends with NO_ACTION)."""
    quat = np.zeros((batch, 4), np.float32)
    quat[:, 0] = 1.0
    return KeyActions(pos=np.zeros((batch, 3), np.float32), quat=quat,
                      gripper=np.ones(batch, np.float32), valid=np.zeros(batch, bool))


# Built-in policies by name, as "module:attr" so that a policy's dependencies
# (an LLM client, a model) load only when it is used.
_REGISTRY: dict[str, str | Callable[..., Policy]] = {
    "oracle": "agnostos_mjx.policies.oracle:OraclePolicy",
    "xicm": "agnostos_mjx.policies.xicm:XICMPolicy",
    "retrieval": "agnostos_mjx.policies.retrieval:RetrievalPolicy",
    "remote": "agnostos_mjx.remote.client:RemotePolicy",
    "openvla": "agnostos_mjx.remote.client:OpenVLAPolicy",
}


def register_policy(name: str, factory: str | Callable[..., Policy]) -> None:
    """Make `name` usable with `make_policy` / ``--policy``: `factory` is a
    class, a function returning a Policy, or a "module:attr" string."""
    _REGISTRY[name] = factory


def list_policies() -> list[str]:
    return sorted(_REGISTRY)


def load_object(spec: str) -> Any:
    """Import "package.module:attr" or "path/to/file.py:attr" (attr may be dotted)."""
    module_name, sep, attr = spec.partition(":")
    if not sep or not module_name or not attr:
        raise ValueError(f"expected 'module:attr' or 'file.py:attr', got {spec!r}")
    if module_name.endswith(".py"):
        path = Path(module_name).expanduser().resolve()
        if not path.is_file():
            raise ImportError(f"no such policy file: {path}")
        mod_spec = importlib.util.spec_from_file_location(f"_agnostos_policy_{path.stem}", path)
        assert mod_spec is not None and mod_spec.loader is not None
        module = importlib.util.module_from_spec(mod_spec)
        sys.modules[mod_spec.name] = module
        mod_spec.loader.exec_module(module)
    else:
        module = importlib.import_module(module_name)
    obj: Any = module
    for part in attr.split("."):
        try:
            obj = getattr(obj, part)
        except AttributeError:
            raise ImportError(f"{module_name!r} has no attribute {attr!r}") from None
    return obj


def make_policy(spec: str, **kwargs: Any) -> Policy:
    """A policy from a registered name or a "module:attr" / "file.py:attr" string.

    The target may be a class or a factory (called with `kwargs`) or an
    instance (used as is; kwargs must then be empty).  A policy without a
    `name` attribute is named after `spec`."""
    target = _REGISTRY.get(spec, spec)
    if isinstance(target, str):
        if ":" not in target:
            raise KeyError(f"unknown policy {spec!r}; registered policies: "
                           f"{', '.join(list_policies())}; or give 'module:attr'")
        target = load_object(target)
    if isinstance(target, type) or not (hasattr(target, "act") and hasattr(target, "reset")):
        if not callable(target):
            raise TypeError(f"{spec!r} is neither a policy nor a policy factory")
        policy = target(**kwargs)
    else:
        if kwargs:
            raise TypeError(f"{spec!r} is a policy instance; it takes no arguments")
        policy = target
    if not (callable(getattr(policy, "act", None)) and callable(getattr(policy, "reset", None))):
        raise TypeError(f"{spec!r} gave {type(policy).__name__}, which lacks reset()/act()")
    if not getattr(policy, "name", None):
        try:
            policy.name = spec
        except AttributeError:
            pass
    return policy
