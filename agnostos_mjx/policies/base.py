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

The contract has a required part, `Policy` (`name`, `reset`, `act`), and optional
parts, `PolicyExtras`; a policy adds whichever it needs:

* ``observation_spec``: a policy that consumes camera images declares one (an
  `agnostos_mjx.observation.ObservationSpec`: cameras, resolution, modalities); the
  evaluator then renders exactly that with ``episodes.observe(env, spec)`` at every step
  and calls ``policy.act(episodes, env, observation=...)`` with an `RLBenchObservation`
  (RGB, depth, point clouds, segmentation, camera matrices, gripper pose and joints; see
  observation.py).  Policies without one pay for no rendering.
* ``reset(..., episode_seeds=...)``: a seed per world for the policy's own randomness,
  a function of the episode alone (not of the batch it runs in).
* ``act_steps``: `act` as a generator that yields the futures it waits on (LLM
  requests, a policy server's answers), so that other tasks simulate meanwhile.
* ``end_reasons``: per world, the outcome code that explains a ``valid=False`` action
  (bad LLM output, LLM error, ...); 0 leaves it ``no_action``.
* ``episode_info(world)``: what to store with the episode's record (``policy_info``).
* ``report()``: the run's request statistics, as sections of results.json (``llm``,
  ``remote``).
* ``action_modes``: the modes the policy acts in, ("keyaction",) by default; a policy for
  ``--action-mode dense`` declares "dense": its `act` then returns one end-effector target
  per world per control step, or an action chunk (B, H, ...) of them
  (agnostos_mjx/evaluation/dense.py), and ``relative = True`` makes its rows deltas of the
  current tip pose.

The evaluator reaches every policy through `PolicyAdapter`, which supplies the defaults
of the optional parts a policy lacks.

Policies are found by name with `make_policy`: a registered name ("oracle") or
a "module:attr" / "path/to/file.py:attr" string naming a class, a factory
function or a ready instance.  This is the equivalent of X-ICM's custom-agent
template: write a class with `name`, `reset` and `act`, then run
``python -m agnostos_mjx.eval --policy my_pkg.my_module:MyPolicy``.
"""

from __future__ import annotations

import concurrent.futures
import copy
import importlib
import importlib.util
import inspect
import sys
from collections.abc import Callable, Generator, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any, Protocol, runtime_checkable

import numpy as np

from agnostos_mjx.tasks.base import KeyActions

if TYPE_CHECKING:  # the runner imports physics and JAX; keep this module light
    from agnostos_mjx.observation import ObservationSpec, RLBenchObservation
    from agnostos_mjx.runtime.env import Episodes
    from agnostos_mjx.runtime.state import EnvState

ActSteps = Generator[concurrent.futures.Future, Any, KeyActions]


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


class PolicyExtras(Policy, Protocol):
    """A policy with every optional part (see the module docstring); `PolicyAdapter`
    supplies the default of each part a policy lacks."""

    # An ObservationSpec (or a method returning one); default None: act gets no observation.
    observation_spec: ObservationSpec | Callable[[], ObservationSpec | None] | None
    # Per world, an Outcome code for a world given no action (0: plain no_action);
    # default: all 0.
    end_reasons: np.ndarray
    # The action modes it acts in ("keyaction", "dense"); default ("keyaction",).
    action_modes: tuple[str, ...]
    # Dense mode: rows are deltas of the tip pose measured when each row starts; default
    # False (absolute targets).
    relative: bool

    def reset(self, episodes: Episodes, env: EnvState, instructions: list[str],
              episode_seeds: Sequence[int] | None = None) -> None:
        """As Policy.reset; `episode_seeds[i]` seeds world i's own randomness."""
        ...

    def act(self, episodes: Episodes, env: EnvState,
            observation: RLBenchObservation | None = None) -> KeyActions:
        """As Policy.act; `observation` is given when the policy has an observation_spec."""
        ...

    def act_steps(self, episodes: Episodes, env: EnvState,
                  observation: RLBenchObservation | None = None) -> ActSteps:
        """`act` as a generator yielding the futures it waits on; returns the actions.
        Default: `act`, which blocks (no other task runs meanwhile)."""
        ...

    def episode_info(self, world: int) -> dict:
        """What the evaluator stores as ``policy_info`` in world's episode record once it
        finishes.  Default: no policy_info."""
        ...

    def report(self) -> dict[str, Any]:
        """Sections of results.json about the run's requests (``{"llm": {...}}``);
        called as results are written.  Default: none."""
        ...


class PolicyAdapter:
    """A policy behind the whole contract: each optional part it lacks gets its default,
    so the evaluator calls every part and never asks a policy what it has (the asking
    happens here and nowhere else).  Attributes a policy may replace at reset
    (end_reasons, observation_spec) are read at every call."""

    def __init__(self, policy: Policy, default_name: str = "policy") -> None:
        self.policy = policy
        self._default_name = default_name
        self._seeded = _accepts(policy.reset, "episode_seeds")
        # A policy that yields while it waits lets the evaluator overlap tasks.
        self.interleaves = hasattr(policy, "act_steps")

    @property
    def name(self) -> str:
        return getattr(self.policy, "name", self._default_name)

    def copy(self) -> PolicyAdapter:
        """A shallow copy of the policy (shared heavy parts, its own per-batch state, which
        reset() replaces), so that tasks running at once do not share episodes."""
        return PolicyAdapter(copy.copy(self.policy), self._default_name)

    def observation_spec(self) -> ObservationSpec | None:
        spec = getattr(self.policy, "observation_spec", None)
        return spec() if callable(spec) else spec

    def reset(self, episodes: Episodes, env: EnvState, instructions: list[str],
              episode_seeds: Sequence[int]) -> None:
        if self._seeded:
            self.policy.reset(episodes, env, instructions, episode_seeds=list(episode_seeds))
        else:
            self.policy.reset(episodes, env, instructions)

    def _observation(self, episodes: Episodes, env: EnvState) -> dict[str, Any]:
        """act's keyword arguments: the observation its spec asks for, if it has one."""
        spec = self.observation_spec()
        return {} if spec is None else {"observation": episodes.observe(env, spec)}

    def act(self, episodes: Episodes, env: EnvState) -> KeyActions:
        """The next key actions, waiting for them (a caller with nothing else to run)."""
        return self.policy.act(episodes, env, **self._observation(episodes, env))

    def act_steps(self, episodes: Episodes, env: EnvState) -> ActSteps:
        """The next key actions as a generator over the futures the policy waits on."""
        kwargs = self._observation(episodes, env)
        if self.interleaves:
            return (yield from self.policy.act_steps(episodes, env, **kwargs))
        return self.policy.act(episodes, env, **kwargs)

    def action_modes(self) -> tuple[str, ...]:
        """The action modes the policy acts in (default: key actions only)."""
        return tuple(getattr(self.policy, "action_modes", ("keyaction",)))

    def relative(self) -> bool:
        """Whether the policy's dense rows are deltas of the current tip pose."""
        return bool(getattr(self.policy, "relative", False))

    def end_reasons(self, env: EnvState) -> np.ndarray:
        """Per world, the outcome that replaces no_action (0: none)."""
        reasons = getattr(self.policy, "end_reasons", None)
        return np.zeros_like(env.outcome) if reasons is None else reasons

    def episode_info(self, world: int) -> dict | None:
        """The record's policy_info of `world`, None when the policy keeps none."""
        info = getattr(self.policy, "episode_info", None)
        return None if info is None else info(world)

    def report(self) -> dict[str, Any]:
        """Sections of results.json on the run's requests ({} for none)."""
        report = getattr(self.policy, "report", None)
        return {} if report is None else report()


def _accepts(func: Callable, name: str) -> bool:
    try:
        return name in inspect.signature(func).parameters
    except (TypeError, ValueError):
        return False


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
    "dense-replay": "agnostos_mjx.policies.dense_replay:DenseReplayPolicy",
    "xicm": "agnostos_mjx.policies.xicm:XICMPolicy",
    "retrieval": "agnostos_mjx.policies.retrieval:RetrievalPolicy",
    "remote": "agnostos_mjx.remote.client:RemotePolicy",
    "openvla": "agnostos_mjx.remote.client:OpenVLAPolicy",
    "reference-vla": "agnostos_mjx.policies.reference_vla:ReferenceVLAPolicy",
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
