"""The policy contract: what the evaluator asks of a policy, and what a policy sees.

A policy drives a batch of B worlds of one task, one key action per world per round, as an
agent in X-ICM's RLBench loop (one key action per transition).  The evaluator calls

    policy.reset(view)               # once per batch, after Episodes.reset (round 0)
    while not all worlds are done:
        actions = policy.act(view)   # KeyActions, leading axis B
        ...                          # the runtime carries them out; view = view.at(new state)

`view` is a `Round`: what the policy may see of its worlds at this round, namely each
world's instruction and episode seed, which worlds still run, the key actions each has taken,
its proprioception (RLBench's low-dimensional fields), and the camera observation the policy
declared.  The simulator (the task, the scene's state, the expert) is in it only for a
policy that declares `privileged = True`: the oracle replays the expert, and X-ICM and
retrieval textualise the scene's object poses as the paper does.  A learned VLA sees what a
robot would.

Write a policy by subclassing `Policy` and overriding `act` (and `reset` when it keeps state
per batch).  Class (or instance) attributes declare the rest, each with a default:

* ``observation_spec``: an `ObservationSpec` (cameras, resolution, modalities); the round
  then renders it on first use of ``view.observation``.  None (default): nothing rendered.
* ``privileged``: True gives ``view.episodes`` and ``view.env``; default False.
* ``action_modes``: ("keyaction",) by default; a policy for ``--action-mode dense`` declares
  "dense": its `act` then returns one end-effector target per world per control step, or a
  chunk (B, H, ...) of them (evaluation/dense.py), and ``relative = True`` makes its rows
  deltas of the current tip pose.
and these methods: ``act_steps`` (`act` as a generator that yields the futures it waits on,
LLM batches or a policy server's answers, so that other tasks simulate meanwhile),
``episode_info(world)`` (what to store as the episode record's ``policy_info``),
``report()`` (the run's request statistics, as sections of results.json) and, for a
built-in policy, the classmethod ``warm_up(options, batch)`` (its programs compiled once
per machine before a run's processes start).

A world whose action has ``valid=False`` ends with ``Outcome.NO_ACTION``; that is how a
policy says "I have nothing to execute".  Why travels with the action: ``end_reason`` of the
returned `KeyActions`, (B,) `Outcome` codes (``Outcome.BAD_LLM_OUTPUT``, ``LLM_ERROR``, a
server's ``REMOTE_ERROR``, ...; 0: plain ``no_action``) that the world's record then shows
(`no_actions(batch, reason)`).  Worlds that already finished ignore their action.

Policies are found by name with `make_policy`: a registered name ("oracle") or a
"module:attr" / "path/to/file.py:attr" string naming a class, a factory function or a
ready instance.  This is the equivalent of X-ICM's custom-agent template:
``python -m agnostos_mjx.eval --policy my_pkg.my_module:MyPolicy``.
"""

from __future__ import annotations

import concurrent.futures
import copy
import functools
import importlib
import importlib.util
import inspect
import sys
from collections.abc import Callable, Generator, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any, NamedTuple

import numpy as np

from agnostos_mjx.infra.gather import send_alone
from agnostos_mjx.policies.options import PolicyOptions, describe, parse_options
from agnostos_mjx.sim.actions import KeyActions

if TYPE_CHECKING:  # the runner imports physics and JAX; keep this module light
    from agnostos_mjx.runtime.env import Episodes
    from agnostos_mjx.runtime.observation import ObservationSpec, RLBenchObservation
    from agnostos_mjx.runtime.state import EnvState

ActSteps = Generator[concurrent.futures.Future, Any, KeyActions]


class PrivilegedAccessError(AttributeError):
    """A policy that did not declare ``privileged = True`` asked for the simulator."""


class Round:
    """What a policy sees of its batch of worlds at one round (round 0 is the reset).

    Arrays have a leading axis B (padding worlds included).  `observation` renders the
    declared spec once, on first use; `episodes` and `env` are the simulator, there only
    for a privileged policy."""

    def __init__(self, episodes: Episodes, env: EnvState, instructions: Sequence[str],
                 episode_seeds: Sequence[int] | None = None, *,
                 observation_spec: ObservationSpec | None = None,
                 privileged: bool = False) -> None:
        self.instructions = tuple(instructions)
        self.episode_seeds = tuple(int(s) for s in (
            range(len(self.instructions)) if episode_seeds is None else episode_seeds))
        if len(self.episode_seeds) != len(self.instructions):
            raise ValueError(f"{len(self.instructions)} instructions but "
                             f"{len(self.episode_seeds)} episode seeds")
        self.observation_spec = observation_spec
        self.privileged = privileged
        self._episodes, self._env = episodes, env

    @classmethod
    def for_policy(cls, policy: Policy, episodes: Episodes, env: EnvState,
                   instructions: Sequence[str], episode_seeds: Sequence[int] | None = None
                   ) -> Round:
        """Round 0 of a batch, showing what `policy` declared."""
        return cls(episodes, env, instructions, episode_seeds,
                   observation_spec=policy.observation_spec, privileged=policy.privileged)

    def at(self, env: EnvState) -> Round:
        """The same worlds at a later state."""
        return Round(self._episodes, env, self.instructions, self.episode_seeds,
                     observation_spec=self.observation_spec, privileged=self.privileged)

    @property
    def batch(self) -> int:
        return len(self.instructions)

    @property
    def running(self) -> np.ndarray:
        """(B,) bool: worlds whose episode goes on (the others ignore their action)."""
        return ~np.asarray(self._env.done, bool)

    @property
    def key_actions(self) -> np.ndarray:
        """(B,) key actions executed so far (control steps in dense mode)."""
        return np.asarray(self._env.key_actions)

    @functools.cached_property
    def proprioception(self) -> dict[str, np.ndarray]:
        """RLBench's low-dimensional fields of every world: gripper_pose (B, 7; xyz and
        quaternion xyzw), gripper_open, joint_positions, joint_velocities,
        gripper_joint_positions (observation.py)."""
        return self._episodes.observer.proprioception(self._env)

    @functools.cached_property
    def observation(self) -> RLBenchObservation:
        """The declared `observation_spec` of every world, rendered on first use."""
        if self.observation_spec is None:
            raise ValueError("this policy declared no observation_spec, so nothing is rendered "
                             "for it; set observation_spec to an ObservationSpec")
        return self._episodes.observe(self._env, self.observation_spec)

    @property
    def episodes(self) -> Episodes:
        """The runner (task, scene, expert, renderers): privileged policies only."""
        return self._simulator(self._episodes)

    @property
    def env(self) -> EnvState:
        """The worlds' simulator state: privileged policies only."""
        return self._simulator(self._env)

    def _simulator(self, part: Any) -> Any:
        if not self.privileged:
            raise PrivilegedAccessError(
                "the simulator (view.episodes, view.env) is for policies that declare "
                "privileged = True; a policy sees view.instructions, view.observation "
                "(its observation_spec) and view.proprioception")
        return part


def run_blocking(steps: Generator[concurrent.futures.Future, Any, Any]) -> Any:
    """Drive a generator of futures to its return value, waiting on each future (a gathered
    request is sent at once, alone: nothing else runs here)."""
    try:
        future = next(steps)
        while True:
            send_alone(future)  # a gathered request (agnostos_mjx/infra/gather.py), alone
            concurrent.futures.wait([future])
            future = steps.send(None)
    except StopIteration as stop:
        return stop.value


class Policy:
    """One key action per world per round for a batch of episodes of one task (see the
    module docstring).  A subclass overrides `act` or `act_steps`."""

    name: str = "policy"
    observation_spec: ObservationSpec | None = None
    privileged: bool = False
    action_modes: tuple[str, ...] = ("keyaction",)
    relative: bool = False

    def __init_subclass__(cls, **kwargs: Any) -> None:
        super().__init_subclass__(**kwargs)
        if cls.act is Policy.act and cls.act_steps is Policy.act_steps:
            raise TypeError(f"{cls.__name__} must override act (or act_steps)")

    def reset(self, view: Round) -> None:
        """Start a new batch: `view.instructions[i]` is world i's language goal and
        `view.episode_seeds[i]` seeds its own randomness (a function of the episode alone,
        not of the batch it runs in).  Default: nothing kept per batch."""

    def act(self, view: Round) -> KeyActions:
        """The next key action of every world: pos (B, 3) tip position in world
        coordinates, quat (B, 4) wxyz, gripper (B,) open amount in [0, 1] and valid (B,)
        bool; valid=False ends that world with Outcome.NO_ACTION, or with the Outcome code
        of end_reason (B,) where that is given and not 0.  Default: `act_steps`, waiting on
        each future."""
        return run_blocking(self.act_steps(view))

    def act_steps(self, view: Round) -> ActSteps:
        """`act` as a generator that yields the futures it waits on and returns the
        actions.  Default: `act`, which blocks (no other task runs meanwhile)."""
        return self.act(view)
        yield  # noqa: B901 - makes this a generator

    def interleaves(self) -> bool:
        """Whether `act_steps` yields while it waits, so that other tasks can run meanwhile."""
        return type(self).act_steps is not Policy.act_steps

    def episode_info(self, world: int) -> dict | None:
        """What the evaluator stores as ``policy_info`` in world's record once it finishes
        (None: nothing)."""
        return None

    def report(self) -> dict[str, Any]:
        """Sections of results.json about the run's requests (``{"llm": {...}}``); called
        as results are written.  Default: none."""
        return {}

    @classmethod
    def warm_up(cls, options: Any, batch: int) -> bool:
        """Compile, from the policy's options alone, the programs it runs alike at every
        task, so that the processes of a run load them from JAX's persistent cache instead
        of each compiling them at once (agnostos_mjx.warmup does it once per machine, for
        built-in policies whose registry entry says `shared_programs`).  Returns whether
        there was anything to compile; default: nothing."""
        return False

    def fork(self) -> Policy:
        """A shallow copy for a task running beside others: shared heavy parts (an LLM
        client, a model), its own per-batch state, which reset() replaces."""
        return copy.copy(self)


def no_actions(batch: int, reason: int = 0) -> KeyActions:
    """A batch of invalid key actions: every world ends with NO_ACTION, or with the Outcome
    code `reason` when it is not 0."""
    quat = np.zeros((batch, 4), np.float32)
    quat[:, 0] = 1.0
    return KeyActions(pos=np.zeros((batch, 3), np.float32), quat=quat,
                      gripper=np.ones(batch, np.float32), valid=np.zeros(batch, bool),
                      end_reason=np.full(batch, reason, np.int32) if reason else None)


class Builtin(NamedTuple):
    """A built-in policy: its class and its options type (policies/options.py), as
    "module:attr" so that a policy's dependencies (an LLM client, a model, JAX) load only
    when it is used, and its options without them; `shared_programs`: its class overrides
    `Policy.warm_up` (said here so that a run's launcher knows without importing JAX)."""

    policy: str
    options: str
    shared_programs: bool = False


_REGISTRY: dict[str, Builtin | str | Callable[..., Policy]] = {
    "oracle": Builtin("agnostos_mjx.policies.oracle:OraclePolicy",
                      "agnostos_mjx.policies.oracle:OracleOptions"),
    "dense-replay": Builtin("agnostos_mjx.policies.dense_replay:DenseReplayPolicy",
                            "agnostos_mjx.policies.learned_options:DenseReplayOptions"),
    "xicm": Builtin("agnostos_mjx.policies.xicm:XICMPolicy",
                    "agnostos_mjx.policies.learned_options:XicmOptions", shared_programs=True),
    "retrieval": Builtin("agnostos_mjx.policies.retrieval:RetrievalPolicy",
                         "agnostos_mjx.policies.learned_options:RetrievalOptions",
                         shared_programs=True),
    "remote": Builtin("agnostos_mjx.remote.client:RemotePolicy",
                      "agnostos_mjx.remote.options:RemoteOptions"),
    "openvla": Builtin("agnostos_mjx.remote.client:OpenVLAPolicy",
                       "agnostos_mjx.remote.options:OpenVLAOptions"),
    "reference-vla": Builtin("agnostos_mjx.policies.reference_vla:ReferenceVLAPolicy",
                             "agnostos_mjx.policies.learned_options:ReferenceVLAOptions",
                             shared_programs=True),
    "timing": Builtin("agnostos_mjx.policies.timing:TimingPolicy",
                      "agnostos_mjx.policies.timing:TimingOptions"),
}


def register_policy(name: str, factory: str | Callable[..., Policy]) -> None:
    """Make `name` usable with `make_policy` / ``--policy``: `factory` is a
    class, a function returning a Policy, or a "module:attr" string; it gets the
    --policy-arg pairs as keyword arguments."""
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


def options_type(spec: str) -> type[PolicyOptions] | None:
    """The options type of a built-in policy; None for any other, whose factory takes the
    --policy-arg pairs as free keyword arguments."""
    entry = _REGISTRY.get(spec)
    return load_object(entry.options) if isinstance(entry, Builtin) else None


def shares_programs(spec: str) -> bool:
    """Whether `spec` is a built-in policy with programs to compile once per machine
    (`Policy.warm_up`); found without importing the policy."""
    entry = _REGISTRY.get(spec)
    return isinstance(entry, Builtin) and entry.shared_programs


def warm_up_policy(spec: str, batch: int, **kwargs: Any) -> bool:
    """`Policy.warm_up` of the built-in policy `spec`, its options parsed from `kwargs` as
    `make_policy` parses them; False for a policy without shared programs."""
    if not shares_programs(spec):
        return False
    entry = _REGISTRY[spec]
    assert isinstance(entry, Builtin)  # shares_programs says so
    options = parse_options(options_type(spec), kwargs, spec)
    return bool(load_object(entry.policy).warm_up(options, batch))


def policy_help(spec: str) -> str:
    """What ``--policy-arg help`` prints: a built-in policy's options, else the signature
    its --policy-arg pairs are passed to."""
    kind = options_type(spec)
    if kind is not None:
        return describe(kind, spec)
    target = _REGISTRY.get(spec, spec)
    if isinstance(target, str):
        target = load_object(target)
    try:
        signature = str(inspect.signature(target))
    except (TypeError, ValueError):  # an instance, or a builtin without one
        signature = "(none: it is a ready instance)" if isinstance(target, Policy) else "(?)"
    return f"--policy {spec} takes its --policy-arg pairs as keyword arguments: {signature}"


def make_policy(spec: str, **kwargs: Any) -> Policy:
    """A policy from a registered name or a "module:attr" / "file.py:attr" string.

    A built-in policy is constructed from its options, `kwargs` parsed into its options
    type (`parse_options`: an OptionsError for an unknown key or a wrong type).  Any other
    target may be a `Policy` subclass or a factory (called with `kwargs`) or a `Policy`
    instance (used as is; kwargs must then be empty).  A policy that keeps the default
    name is named after `spec`."""
    target = _REGISTRY.get(spec, spec)
    if isinstance(target, Builtin):
        options = parse_options(options_type(spec), kwargs, spec)
        target, kwargs = load_object(target.policy), {"options": options}
    if isinstance(target, str):
        if ":" not in target:
            raise KeyError(f"unknown policy {spec!r}; registered policies: "
                           f"{', '.join(list_policies())}; or give 'module:attr'")
        target = load_object(target)
    if isinstance(target, Policy):
        if kwargs:
            raise TypeError(f"{spec!r} is a policy instance; it takes no arguments")
        policy = target
    elif callable(target):
        policy = target(**kwargs)
    else:
        raise TypeError(f"{spec!r} is neither a policy nor a policy factory")
    if not isinstance(policy, Policy):
        raise TypeError(f"{spec!r} gave a {type(policy).__name__}, not an "
                        "agnostos_mjx.policies.Policy: subclass Policy and override act "
                        "(see agnostos_mjx/policies/base.py)")
    if policy.name == Policy.name:
        policy.name = spec
    return policy
