"""Our batched worlds as a ``gymnasium.vector.VectorEnv``: what LeRobot's ``lerobot-eval``
steps (through the ``lerobot_env_agnostos`` plug-in, which only registers the env type) and
what any gymnasium-speaking policy loop can drive.  Needs gymnasium (>= 1.1), not lerobot
or torch.

One VectorEnv = ``num_envs`` worlds of one task, run as one batched ``Episodes`` (native
MuJoCo by default, ``backend`` as the evaluator's).  Its rows speak the LeRobot export's
layout (data/lerobot_layout.py), for the same ``cameras``, ``size``, ``state`` and
``rotation`` as the export's flags:

* observation ``{"pixels": {camera: uint8 (n, H, W, 3)}, "agent_pos": float32 (n, D)}``,
  which LeRobot's ``preprocess_observation`` turns into exactly the export's keys,
  ``observation.images.<camera>`` and ``observation.state`` (``lerobot_features`` names
  the mapping); the images and the state come from the same renderer and ``state_vector``
  as the export's frames;
* action float32 (n, D): one key action per world, the export's ``action`` row: the
  absolute world-frame tip target x y z, its orientation in ``rotation``, the gripper's open
  amount in [0, 1] (read by the policy-server adapter's ``parse_rows``, so the rotation
  conventions are the adapter's and the export's).  A row that is no key action (not
  finite, a zero quaternion) ends that world's episode as ``no_action``.

``control_mode``: ``keyaction`` (one step = one key action through the planner, as the
AGNOSTOS protocol and X-ICM's harness run policies; ``_max_episode_steps`` = the task's 25
key actions) or ``dense`` (one step = one control period at ``control_hz``, default 20, the
rate of the export's ``--every rlbench`` frames: the row is an end-effector target reached
by IK and physics without the planner, runtime/dense.py; ``_max_episode_steps`` = the dense
step budget, ``dense_steps`` or by default 25 key actions x 2 s: 1000 steps at 20 Hz; the
render fps is the control rate).

Episodes follow the evaluation protocol (evaluation/protocol.py): gymnasium seed ``g`` of a
world is episode ``g`` of protocol seed ``protocol_seed``, scene key ``fold_in(PRNGKey(
protocol_seed), g)`` and its protocol variation, so ``reset(seed=0)`` on 25 worlds is the
evaluator's 25 episodes of that seed (``reset(seed=int)`` seeds world i with g + i, as
gymnasium's vector envs do; a list gives each world's own).  ``reset()`` without a seed
goes on to the next ``num_envs`` episodes, from 0 if never seeded: same calls, same
episodes.  ``reset(options={"episode_keys": (n, 2) uint32, "variations": (n,)})`` starts
explicit scenes instead (e.g. an exported demo's, data/generate.py ``demo_keys``).

An episode ends ``terminated`` at its first success or a failure outcome (planner refusal,
failure condition, no action) and ``truncated`` after the budget of key actions;
``info["is_success"]`` says which ended in success, ``info["outcome"]`` the
``runtime.outcome.Outcome`` code.  Autoreset (gymnasium 1.x, ``metadata["autoreset_mode"]``):
``next_step`` (default, gymnasium's own default and what lerobot-eval's rollout reads:
``info["is_success"]`` at the ending step; the step after it resets that world and ignores
its action) or ``same_step`` (the ending step returns the new episode's observation, the
ended one's in ``info["final_obs"]`` and its info in ``info["final_info"]``, as lerobot's
own ``create_envs`` asks of gymnasium).  A reset world starts the next episode of its seed
sequence: g + num_envs.

``renderer``: where the images render (auto: MJX-Warp's ray tracer wherever a GPU with
warp-lang is, else MuJoCo's OpenGL on the CPU; cpu; warp), as the evaluator's
``--renderer``.  The export renders as the evaluator does on its machine (its
``--renderer``); its datasets record the renderer and the scene version (data/look.py).
An env given its policy's ``training_data`` (the dataset's meta/info.json as a dict; the
plug-in passes it) logs one warning line, once per process, at its first reset when it
renders otherwise (:func:`look_warning`; ``renderer="cpu"``
renders as the export did).  Not before: resolving ``auto`` starts JAX, whose GPU memory
pool would then be taken before LeRobot loads its policy.

The options, spaces and policy checks are gym/options.py's; ``agnostos_mjx.gym_env`` is
the public door to both.

``call(name)`` / ``get_attr(name)`` return one value per world, as gymnasium's vector envs
do: ``task_description`` (each world's instruction, what lerobot-eval gives the policy as
``task``), ``task`` (the task's name), ``_max_episode_steps``, ``render``.  ``render()``:
each world's frame of ``render_camera`` (uint8 H x W x 3; lerobot-eval's videos).
"""

from __future__ import annotations

import logging
from collections.abc import Mapping, Sequence
from fractions import Fraction
from typing import Any

import gymnasium as gym
import numpy as np
from gymnasium.vector.utils import batch_space

from agnostos_mjx.data.lerobot import KEYFRAME_FPS  # the export's nominal rate; videos play at it
from agnostos_mjx.data.lerobot_layout import action_vector, state_vector
from agnostos_mjx.gym.options import (
    AUTORESET_MODES,
    EnvOptions,
    look_warning,
    single_spaces,
)
from agnostos_mjx.tasks.base import KeyActions, Split

# LeRobot-facing suite names -> our splits (--env.task=level1 runs every level-1 task).
SUITES: dict[str, Split] = {"seen": Split.SEEN, "level1": Split.LEVEL1, "level2": Split.LEVEL2}
# Reset options: explicit scenes, and the flag lerobot-eval's rollout passes to mark a new
# rollout (for its FreezeAfterEpisodeEnd wrapper; ignored here).
KNOWN_OPTIONS = {"episode_keys", "variations", "lerobot_new_rollout"}
# The public module's name (agnostos_mjx.gym_env), the logger its users configure.
log = logging.getLogger("agnostos_mjx.gym_env")
_warned: set[str] = set()  # look warnings already logged by this process


def resolve_tasks(spec: str) -> dict[str, list[str]]:
    """``--env.task``: a suite (seen, level1, level2, unseen = both levels), task names,
    or a comma-separated mix -> {suite: [task names]} in the order named (a suite in
    benchmark order), each once; a clear
    ValueError for anything else."""
    from agnostos_mjx.tasks import get_task, list_tasks

    if not isinstance(spec, str) or not spec.strip():
        raise ValueError(f"task must name a task or a suite ({', '.join(SUITES)}, unseen)")
    suite_of = {split: name for name, split in SUITES.items()}
    out: dict[str, list[str]] = {}
    for part in (p.strip() for p in spec.split(",") if p.strip()):
        if part == "unseen":
            names = list_tasks(Split.LEVEL1) + list_tasks(Split.LEVEL2)
        elif part in SUITES:
            names = list_tasks(SUITES[part])
        else:
            try:
                names = [get_task(part).name]
            except KeyError as e:
                raise ValueError(f"unknown task or suite {part!r}: suites are "
                                 f"{', '.join(SUITES)}, unseen; {e.args[0]}") from None
        for name in names:
            suite = suite_of[get_task(name).split]
            if name not in out.setdefault(suite, []):
                out[suite].append(name)
    return out


def make_suites(task: str, num_envs: int, training_data: Mapping[str, Any] | None = None,
                renderer_flag: str = "renderer", **options: Any
                ) -> dict[str, dict[int, AgnostosVectorEnv]]:
    """``{suite: {task_id: VectorEnv}}`` (what LeRobot's ``EnvConfig.create_envs``
    returns): one env of `num_envs` worlds per task; each builds its scene at first use,
    so naming a whole suite costs nothing until it runs.  `training_data`,
    `renderer_flag`: AgnostosVectorEnv's."""
    opts = EnvOptions(**options)
    return {suite: {i: AgnostosVectorEnv(name, num_envs, opts, training_data=training_data,
                                         renderer_flag=renderer_flag)
                    for i, name in enumerate(names)}
            for suite, names in resolve_tasks(task).items()}


def video_fps(hz: float) -> int | Fraction:
    """A control rate as a video's frame rate: an int, or an exact fraction when the rate is
    not whole (LeRobot's video writer hands it to PyAV, which takes no float)."""
    return int(hz) if float(hz).is_integer() else Fraction(hz).limit_denominator(1000)


def _owned(a: np.ndarray) -> np.ndarray:
    """`a`, or a copy of it where it is read-only (the GPU route's images are JAX's host
    buffers): an observation is the caller's to change, and ``torch.from_numpy`` (LeRobot's
    ``preprocess_observation``) warns on every read-only one."""
    return a if a.flags.writeable else a.copy()


def _where_rows(mask: np.ndarray, new: Any, old: Any) -> Any:
    """Per world: `new`'s rows where `mask`, else `old`'s (a pytree of (B, ...) leaves)."""
    import jax

    def pick(a, b):
        a, b = np.asarray(a), np.asarray(b)
        return np.where(mask.reshape(-1, *([1] * (a.ndim - 1))), a, b)

    return jax.tree.map(pick, new, old)


class AgnostosVectorEnv(gym.vector.VectorEnv):
    """`num_envs` worlds of one task (module docstring)."""

    def __init__(self, task: str, num_envs: int = 1, options: EnvOptions | None = None,
                 training_data: Mapping[str, Any] | None = None,
                 renderer_flag: str = "renderer", **kwargs: Any) -> None:
        """`training_data`: the policy's dataset's meta/info.json, to warn at the first
        reset when it was rendered otherwise (module docstring); `renderer_flag`: how the
        warning names the option that renders as the data did."""
        from agnostos_mjx.infra.settings import configure_jax
        from agnostos_mjx.tasks import get_task

        # The env is an entry point (lerobot-eval, a gymnasium script): JAX is set up as the
        # commands set it up, which takes effect when this is the process's first JAX use.
        configure_jax()
        if options is not None and kwargs:
            raise ValueError("give EnvOptions or keyword options, not both")
        self.options = opts = options or EnvOptions(**kwargs)
        try:
            self._task = get_task(task)
        except KeyError as e:
            raise ValueError(e.args[0]) from None
        if not isinstance(num_envs, int) or num_envs < 1:
            raise ValueError(f"num_envs must be a positive integer, got {num_envs!r}")
        if opts.variations.isdigit() and int(opts.variations) >= self._task.num_variations:
            raise ValueError(f"variations {opts.variations}: {task} has variations "
                             f"0..{self._task.num_variations - 1}")
        self.num_envs = num_envs
        self.task = self._task.name
        self.render_mode = "rgb_array"
        dense = opts.control_mode == "dense"
        self.metadata = {"render_modes": ["rgb_array"],
                         "render_fps": video_fps(opts.control_hz) if dense else KEYFRAME_FPS,
                         "autoreset_mode": AUTORESET_MODES[opts.autoreset_mode]}
        self.single_observation_space, self.single_action_space = single_spaces(opts)
        self.observation_space = batch_space(self.single_observation_space, num_envs)
        self.action_space = batch_space(self.single_action_space, num_envs)
        self._step_fn = self._dense_step if dense else self._key_action_step
        self._dense_control = None  # dense: runtime.dense.DenseControl, made with the runner
        self._episodes = None  # the batched runner, built at the first reset
        self._state = None
        self._episode: np.ndarray | None = None  # each world's protocol episode number
        self._needs_reset = np.zeros(num_envs, bool)
        self._instructions: tuple[str, ...] = ("",) * num_envs
        self._last_obs: dict | None = None
        self._look: tuple[Mapping[str, Any], str] | None = (
            None if training_data is None else (training_data, renderer_flag))

    # ---- what lerobot-eval reads ----------------------------------------------------------
    @property
    def task_description(self) -> tuple[str, ...]:
        """Each world's instruction (its variation's first description)."""
        return self._instructions

    @property
    def _max_episode_steps(self) -> int:
        """Steps per episode: the task's key actions, or the dense step budget."""
        if self.options.control_mode == "dense":
            return self.dense_control.max_steps
        return self._task.max_key_actions

    @property
    def dense_control(self):
        """Dense mode's control period and step budget (built with the runner)."""
        if self._dense_control is None:
            from agnostos_mjx.runtime.dense import DenseControl

            self._dense_control = DenseControl.at(
                self.options.control_hz, self.runner.dt, self._task.max_key_actions,
                self.options.dense_steps)
        return self._dense_control

    @property
    def runner(self):
        """The batched ``Episodes`` (built on first use)."""
        if self._episodes is None:
            from agnostos_mjx.runtime.env import Episodes

            self._episodes = Episodes(self._task, self.options.backend)
        return self._episodes

    def get_attr(self, name: str) -> tuple:
        """One value per world (gymnasium's vector API)."""
        if name == "task_description":
            return tuple(self._instructions)
        return (getattr(self, name),) * self.num_envs

    def call(self, name: str, *args: Any, **kwargs: Any) -> tuple:
        """Call `name` (or read it, when not callable); one result per world."""
        if name == "render":
            return self.render()
        if name == "task_description":
            return tuple(self._instructions)
        value = getattr(self, name)
        if callable(value):
            value = value(*args, **kwargs)
        return (value,) * self.num_envs

    # ---- reset ---------------------------------------------------------------------------
    def reset(self, *, seed: int | Sequence[int] | None = None,
              options: dict[str, Any] | None = None) -> tuple[dict, dict]:
        options = dict(options or {})
        unknown = set(options) - KNOWN_OPTIONS
        if unknown:
            raise ValueError(f"unknown reset options {sorted(unknown)}; known: "
                             f"episode_keys, variations")
        if seed is not None and not isinstance(seed, (int, np.integer)) and \
                len(seed) != self.num_envs:
            raise ValueError(f"seed: one integer or {self.num_envs} integers, got {len(seed)}")
        super().reset(seed=None if seed is None else int(np.ravel(seed)[0]))
        if self._look is not None:  # the training data's look, checked once
            data, flag = self._look
            self._look = None
            text = look_warning(data, self.options, flag)
            if text and text not in _warned:
                _warned.add(text)
                log.warning("%s", text)
        if "episode_keys" in options:
            keys = np.asarray(options["episode_keys"], np.uint32)
            if keys.shape != (self.num_envs, 2):
                raise ValueError(f"episode_keys: shape ({self.num_envs}, 2), got {keys.shape}")
            variations = np.asarray(options.get("variations", np.zeros(self.num_envs)), np.int32)
            self._episode = np.full(self.num_envs, -1, np.int64)
            state = self.runner.reset(keys, variations.reshape(self.num_envs))
        else:
            if "variations" in options:
                raise ValueError("reset option variations goes with episode_keys")
            self._episode = self._seeded(seed)
            state = self._reset_episodes(self._episode)
        self._state = state
        self._needs_reset[:] = False
        self._set_instructions(np.ones(self.num_envs, bool))
        obs = self._observe()
        return obs, self._info(np.zeros(self.num_envs, bool))

    def _seeded(self, seed) -> np.ndarray:
        if seed is None:
            start = (np.arange(self.num_envs) if self._episode is None or (self._episode < 0).any()
                     else self._episode + self.num_envs)
            return np.asarray(start, np.int64)
        seeds = np.asarray(seed, np.int64)
        seeds = seeds + np.arange(self.num_envs) if seeds.ndim == 0 else seeds.reshape(-1)
        if (seeds < 0).any() or (seeds >= 2**32).any():
            raise ValueError(f"seeds must lie in 0..2**32-1, got {seeds.tolist()}")
        return seeds

    def _reset_episodes(self, episodes: np.ndarray):
        """Every world reset to its protocol episode (`episodes`, one per world)."""
        from agnostos_mjx.evaluation.protocol import episode_keys, episode_variations

        task = self._task
        keys = episode_keys(np.full(self.num_envs, self.options.protocol_seed), episodes)
        variations = episode_variations(keys, task.num_variations, task.split.value,
                                        self.options.variations)
        return self.runner.reset(keys, variations)

    def _set_instructions(self, worlds: np.ndarray) -> None:
        variations = np.asarray(self._state.variation)
        self._instructions = tuple(
            self._task.descriptions(int(variations[i]))[0] if worlds[i] else old
            for i, old in enumerate(self._instructions))

    def _autoreset(self, worlds: np.ndarray) -> None:
        """Start the next episode of each of `worlds`' seed sequence (the others keep
        theirs): the whole batch is reset, so every world's scene stays a function of its
        episode alone, and the chosen rows are kept."""
        nxt = np.where(worlds, self._episode + self.num_envs, self._episode)
        if (self._episode < 0).any():  # explicit scenes: go on with the protocol's
            nxt = np.where(self._episode < 0, np.arange(self.num_envs), nxt)
        fresh = self._reset_episodes(nxt)
        self._state = _where_rows(worlds, fresh, self._state.to_host())
        self._episode = np.where(worlds, nxt, self._episode)
        self._set_instructions(worlds)

    # ---- step ----------------------------------------------------------------------------
    def step(self, actions: np.ndarray):
        if self._state is None:
            raise RuntimeError("call reset() before step()")
        rows = np.asarray(actions, np.float64)
        want = (self.num_envs, self.options.action_dim)
        if rows.shape != want:
            raise ValueError(f"actions: shape {want} (x y z, {self.options.rotation}, gripper "
                             f"per world), got {rows.shape}")
        resetting = self._needs_reset.copy()
        if resetting.any():  # next_step autoreset: these worlds' actions are ignored
            self._autoreset(resetting)
            self._needs_reset[:] = False
        from agnostos_mjx.runtime.outcome import Outcome

        before = np.asarray(self._state.done).copy()
        fresh = self._state
        self._state = self._step_fn(fresh, rows, ~resetting & ~before)
        if resetting.any():  # the runtime ends a world without an action: keep them fresh
            self._state = _where_rows(resetting, fresh.to_host(), self._state.to_host())
        outcome = np.asarray(self._state.outcome)
        ended = np.asarray(self._state.done) & ~before & ~resetting
        truncated = ended & (outcome == Outcome.MAX_STEPS)
        terminated = ended & ~truncated
        success = ended & (outcome == Outcome.SUCCESS)
        reward = success.astype(np.float64)
        info = self._info(success)
        if self.options.autoreset_mode == "same_step" and ended.any():
            final_obs = self._observe()
            final = np.full(self.num_envs, None, object)
            for i in np.nonzero(ended)[0]:
                final[i] = {"pixels": {c: v[i] for c, v in final_obs["pixels"].items()},
                            "agent_pos": final_obs["agent_pos"][i]}
            final_info = {**info, "_is_success": ended.copy()}
            self._autoreset(ended)
            info = self._info(np.zeros(self.num_envs, bool))
            info.update({"final_obs": final, "_final_obs": ended, "final_info": final_info,
                         "_final_info": ended.copy()})
        else:
            self._needs_reset = ended
        return self._observe(), reward, terminated, truncated, info

    def _key_action_step(self, state, rows: np.ndarray, running: np.ndarray):
        """One key action per running world from the export-layout rows."""
        return self.runner.step(state, self._targets(rows, running))[0]

    def _dense_step(self, state, rows: np.ndarray, running: np.ndarray):
        """One control period per running world toward the export-layout rows."""
        return self.runner.step_dense(state, self._targets(rows, running),
                                      self.dense_control)[0]

    def _targets(self, rows: np.ndarray, running: np.ndarray) -> KeyActions:
        """The rows as targets (tip pose, gripper); a row that is none is not valid."""
        from agnostos_mjx.remote.adapter import Adapter, BadAnswer, parse_rows

        adapter = Adapter(action_key=None, rotation=self.options.rotation)
        n = self.num_envs
        pos, quat = np.zeros((n, 3), np.float32), np.tile([1.0, 0, 0, 0], (n, 1))
        grip, valid = np.ones(n, np.float32), running.copy()
        for i in np.nonzero(running)[0]:
            try:
                p, q, g = parse_rows(adapter, rows[i])[0]
            except BadAnswer:
                valid[i] = False  # the world ends as no_action
                continue
            pos[i], quat[i], grip[i] = p, q, g
        return KeyActions(pos=pos, quat=quat.astype(np.float32), gripper=grip, valid=valid)

    # ---- observation ---------------------------------------------------------------------
    def _observe(self) -> dict:
        from agnostos_mjx.runtime.observation import ObservationSpec

        opts = self.options
        spec = ObservationSpec(cameras=opts.cameras, height=opts.size, width=opts.size,
                               renderer=opts.renderer)
        obs = self.runner.observe(self._state, spec)
        state = state_vector(opts.state, np.asarray(obs.gripper_pose, np.float32),
                             np.asarray(obs.gripper_open, np.float32),
                             np.asarray(obs.gripper_joint_positions, np.float32))
        self._last_obs = {"pixels": {c: _owned(np.asarray(obs.cameras[c].rgb, np.uint8))
                                     for c in opts.cameras},
                          "agent_pos": np.asarray(state, np.float32)}
        return self._last_obs

    def _info(self, success: np.ndarray) -> dict:
        outcome = np.asarray(self._state.outcome)
        return {"is_success": np.asarray(success, bool).copy(),
                "outcome": outcome.astype(np.int64),
                "key_actions": np.asarray(self._state.key_actions, np.int64).copy(),
                "episode": np.asarray(self._episode, np.int64).copy()}

    def expert_actions(self) -> tuple[np.ndarray, np.ndarray]:
        """The task's expert key actions for the current scenes as the export writes them
        (its ``action`` rows, (n, K, D)) and which are real (n, K): a replayable
        reference for the action layout."""
        if self._state is None:
            raise RuntimeError("call reset() before expert_actions()")
        acts = self.runner.expert_actions(self._state)
        quat = np.asarray(acts.quat, np.float64)[..., [1, 2, 3, 0]]
        pose = np.concatenate([np.asarray(acts.pos, np.float64), quat], -1)
        n, k = pose.shape[:2]
        rows = action_vector(self.options.rotation, pose.reshape(n * k, 7),
                             np.asarray(acts.gripper).reshape(n * k))
        return rows.reshape(n, k, -1), np.asarray(acts.valid, bool)

    def render(self) -> tuple[np.ndarray, ...]:
        """Each world's frame of ``render_camera`` (uint8 H x W x 3), for videos."""
        if self._state is None:
            raise RuntimeError("call reset() before render()")
        opts = self.options
        size = opts.render_size or opts.size
        if opts.render_camera in opts.cameras and size == opts.size and self._last_obs:
            frames = self._last_obs["pixels"][opts.render_camera]
        else:
            frames = self.runner.render(self._state, opts.render_camera, size, size)
        return tuple(np.asarray(frames, np.uint8))

    def close_extras(self, **kwargs: Any) -> None:
        if self._episodes is not None:
            self._episodes.close()
            self._episodes = None
