"""Batched episodes: reset B worlds, execute one key action for all of them,
check success at every physics step.  Task-agnostic: everything task-specific
comes through the Task's sampler, conditions and observables.
"""

from __future__ import annotations

import contextlib
import enum
import functools
import logging
from dataclasses import dataclass, field

import jax
import jax.numpy as jnp
import numpy as np

from agnostos_mjx import control, sharding
from agnostos_mjx.control import PandaKinematics, Status
from agnostos_mjx.math3d import quat_conj, quat_mul, quat_rotate
from agnostos_mjx.observables import Observation
from agnostos_mjx.physics import PhysicsState, make_backend, resolve_backend
from agnostos_mjx.tasks.base import KeyActions, Task
from agnostos_mjx.visual_state import StateColors
from agnostos_mjx.world import FINGER_OPEN, SceneModel, apply_placement, build_scene, posed_data

log = logging.getLogger(__name__)
SETTLE_STEPS = 10  # RLBench runs 10 physics steps after placing the scene
GRIPPER_OPEN_THRESHOLD = 0.95  # PerAct fork: gripper_open = open amount > 0.95
# Attach volume between the fingers in the tip frame (RLBench's attach proximity
# sensor: 0.02 x 0.10 m face, 0.045 m deep along the approach axis).
ATTACH_CENTER = np.array([0.0, 0.0, -0.018])
ATTACH_HALF = np.array([0.01, 0.05, 0.0275])


class Outcome(enum.IntEnum):
    RUNNING = 0
    SUCCESS = 1
    MAX_STEPS = 2
    OUT_OF_WORKSPACE = 3
    UNREACHABLE = 4
    INVALID_ACTION = 5
    FAILURE_CONDITION = 6
    NO_ACTION = 7  # the policy had nothing valid to execute (e.g. bad LLM output)
    POLICY_ERROR = 8  # the policy raised
    BAD_LLM_OUTPUT = 9  # the LLM's answer held no valid 7-integer action
    LLM_ERROR = 10  # an LLM request still failed after its retries
    # A served policy (--policy remote): new codes go last so stored codes keep their meaning.
    REMOTE_ERROR = 11  # the policy server refused, dropped the connection or raised
    REMOTE_TIMEOUT = 12  # the policy server did not answer within the timeout
    BAD_REMOTE_OUTPUT = 13  # the server's answer could not be read as a key action

    @property
    def label(self) -> str:
        return self.name.lower()


_STATUS_OUTCOME = {
    Status.OUT_OF_WORKSPACE: Outcome.OUT_OF_WORKSPACE,
    Status.UNREACHABLE: Outcome.UNREACHABLE,
    Status.INVALID_ACTION: Outcome.INVALID_ACTION,
}


@dataclass
class EnvState:
    """Host-side bookkeeping for a batch of episodes."""

    physics: PhysicsState
    obs: Observation  # latest observation per world, data (B, nsensordata)
    carry: tuple  # (success carry, failure carry) of the condition trees
    variation: np.ndarray
    gripper: np.ndarray  # commanded finger position per world
    outcome: np.ndarray  # Outcome per world
    key_actions: np.ndarray  # key actions executed so far
    sim_steps: np.ndarray
    geom_rgba: np.ndarray
    initial_obs: Observation = field(repr=False, default=None)
    # Evaluation ends an episode at its first success (X-ICM stops mid-path);
    # demonstrations run the expert to its end, as RLBench records them.
    stop_at_success: bool = True

    @property
    def done(self) -> np.ndarray:
        if self.stop_at_success:
            return self.outcome != Outcome.RUNNING
        return (self.outcome != Outcome.RUNNING) & (self.outcome != Outcome.SUCCESS)

    @property
    def attached(self) -> np.ndarray:
        return np.asarray(self.obs.attached)


def xicm_actions(ints) -> KeyActions:
    """X-ICM's 7-integer key actions (B, 7) -> KeyActions; groups outside the
    valid ranges become invalid actions (the episode then ends as no_action)."""
    from agnostos_mjx.textualise import decode_action, validate_action_ints

    ints = np.asarray(ints)
    valid = np.asarray(validate_action_ints(ints), bool)
    safe = np.where(valid[:, None], ints, np.array([57, 49, 87, 0, 39, 0, 1]))
    pos, quat, grip = map(np.asarray, decode_action(safe))
    return KeyActions(pos, quat, grip, valid)


@dataclass(frozen=True)
class StepResult:
    """Per-step sensordata of the last key action (arm then gripper phase)."""

    sensordata: np.ndarray  # (B, T, nsensordata)
    attached: np.ndarray  # (B, T, ngraspable)
    valid: np.ndarray  # (B, T): False after a world finished
    # (B, T, nq) qpos after each step when Episodes.record_qpos (native backend), else None
    qpos: np.ndarray | None = None


def reachable_host(kin: PandaKinematics, q, pos, quat, valid) -> np.ndarray:
    """Whether each world's key actions (B, K) are inside the bounds and solvable by IK
    near the expert's branch, warm-started along the sequence (numpy, float64)."""
    ok = np.ones(len(q), bool)
    for k in range(pos.shape[1]):
        p, r = pos[:, k].astype(np.float64), quat[:, k].astype(np.float64)
        q_k, ok_k, _, _ = control.solve_ik(kin, q, p, r, spread=False)
        ok &= ~valid[:, k] | (ok_k & control.within_bounds(p))
        q = np.where(valid[:, None, k], q_k, q)
    return ok


def reachable_device(kin: PandaKinematics, q, pos, quat, valid) -> jax.Array:
    """`reachable_host` as one jitted program (a scan over key actions) for the MJX
    backends on an accelerator, where thousands of worlds reset at once."""

    def body(carry, action):
        q, ok = carry
        p, r, v = action
        q_k, ok_k, _, _ = control.solve_ik(kin, q, p, r, spread=False)
        ok = ok & (~v | (ok_k & control.within_bounds(p)))
        return (jnp.where(v[:, None], q_k, q), ok), None

    xs = (jnp.swapaxes(jnp.asarray(pos, jnp.float32), 0, 1),
          jnp.swapaxes(jnp.asarray(quat, jnp.float32), 0, 1), jnp.swapaxes(jnp.asarray(valid), 0, 1))
    q = jnp.asarray(q, jnp.float32)
    (_, ok), _ = jax.lax.scan(body, (q, jnp.ones(q.shape[0], bool)), xs)
    return ok


class Episodes:
    """Runs batches of episodes of one task on one backend."""

    # StepResults carry each step's qpos (native backend only), to render in-between frames.
    record_qpos: bool = False

    def __init__(self, task: Task, backend: str = "auto", threads: int | None = None):
        self.task = task
        self.scene: SceneModel = build_scene(task)
        self.backend_name = resolve_backend(backend)
        self.backend = make_backend(self.backend_name, self.scene.model, threads)
        self.kin = PandaKinematics.from_model(self.scene.model)
        self.dt = float(self.scene.model.opt.timestep)
        self.nu = self.scene.model.nu
        self._arm_q = self.scene.layout.slice("arm_q")
        self._jit_sample = jax.jit(jax.vmap(self._sample_one))
        self._jit_init_cond = jax.jit(jax.vmap(self._init_conditions))
        self._jit_conditions = jax.jit(jax.vmap(self._conditions))
        # Control runs where the physics runs: jitted on device next to MJX,
        # plain numpy next to native MuJoCo (see control.py).
        self.on_device = self.backend_name != "native" and jax.default_backend() != "cpu"
        self.on_mjx = self.backend_name != "native"
        # The key-action planner of the device path: one program for every task of a run.
        self._device_plan = control.jit_for_robot(control.plan_arm, self.kin)
        self._device_steps: dict = {}  # batch size -> KeyActionStep (compiled once each)
        if not self.on_device:
            self._plan = lambda q, p, r: control.plan_arm(self.kin, q, p, r)
            self._reachable = functools.partial(reachable_host, self.kin)
        else:
            self._plan = control.jit_for_robot(control.plan_arm, self.kin)
            self._reachable = control.jit_for_robot(reachable_device, self.kin)
        self._jit_expert = jax.jit(jax.vmap(task.expert))
        self._jit_attach = jax.jit(jax.vmap(self._attach_test))
        self._state_colors = StateColors(task, self.scene.model, self.scene.layout)
        self._renderer = None
        self._jit_rows: int | None = None  # batch the jitted reset helpers run at

    # ---- pure pieces (vmapped above) -------------------------------------------------
    def _sample_one(self, key, variation):
        return apply_placement(self.scene, self.task.sample(key, variation))

    def _obs(self, data, attached):
        return Observation(data, self.scene.layout, attached)

    def _init_conditions(self, data, attached, variation):
        obs = self._obs(data, attached)
        return (self.task.success(variation).init(obs), self.task.failure(variation).init(obs))

    def _conditions(self, carry, data, attached, valid, variation):
        """Scan the condition trees over one world's steps: (carry, success
        step index or -1, failure step index or -1)."""
        def body(c, inputs):
            d, a, v = inputs
            new, s, f = self._condition_step(c, d, a, variation)
            keep = lambda new, old: jax.tree.map(lambda n, o: jnp.where(v, n, o), new, old)  # noqa: E731
            return keep(new, c), (s & v, f & v)

        carry, (s, f) = jax.lax.scan(body, carry, (data, attached, valid))
        first = lambda m: jnp.where(jnp.any(m), jnp.argmax(m), -1)  # noqa: E731
        return carry, first(s), first(f)

    def _condition_step(self, carry, data, attached, variation):
        """One physics step of one world's success and failure trees: (carry, met, failed)."""
        obs = self._obs(data, attached)
        sc, s = self.task.success(variation).step(carry[0], obs)
        fc, f = self.task.failure(variation).step(carry[1], obs)
        return (sc, fc), jnp.asarray(s, bool), jnp.asarray(f, bool)

    def _attach_test(self, data, attached):
        """Which graspables lie in the attach volume (RLBench's grasp on close)."""
        obs = self._obs(data, attached)
        tip_p, tip_q = obs["tip.pos"], obs["tip.quat"]
        hits = []
        for frame, radius in zip(self.task.grasp_frames, self.task.graspable_radius):
            local = quat_rotate(quat_conj(tip_q), obs.pos(frame) - tip_p) - ATTACH_CENTER
            gap = jnp.linalg.norm(jnp.maximum(jnp.abs(local) - ATTACH_HALF, 0.0))
            hits.append(gap <= radius)
        return jnp.stack(hits) if hits else jnp.zeros((0,), bool)

    # ---- host-side orchestration ------------------------------------------------------
    def reset(self, keys: jax.Array, variations, placement_tries: int = 20,
              stop_at_success: bool = True) -> EnvState:
        """Sample B initial scenes and settle them (RLBench's 10 steps).

        As RLBench does, a scene whose expert waypoints the arm cannot reach is
        re-sampled (from keys folded with the attempt number, so results stay
        deterministic per key).  RLBench retries 5 times; our workspace extent
        is inferred and reaches further than the arm for some layouts, so we
        allow more tries."""
        variations = np.asarray(variations, np.int32)
        if np.any((variations < 0) | (variations >= self.task.num_variations)):
            raise ValueError(
                f"{self.task.name} has variations 0..{self.task.num_variations - 1}, "
                f"got {sorted(set(variations.tolist()))}"
            )
        keys = jnp.asarray(keys)
        b = len(variations)
        self._jit_rows = b
        sampled = list(map(np.asarray, self._jit_sample(keys, variations)))
        env = self._settle(sampled, variations)
        ok = np.array(self.expert_reachable(env), copy=True)
        for attempt in range(1, placement_tries):
            if ok.all():
                break
            # Only the rejected scenes are settled and checked again (in a padded batch,
            # so jitted shapes stay few); every world is settled once more at the end.
            retry = jax.vmap(jax.random.fold_in, in_axes=(0, None))(keys, attempt)
            fresh = list(map(np.asarray, self._jit_sample(retry, variations)))
            bad = ~ok
            sampled = [np.where(bad.reshape(-1, *([1] * (a.ndim - 1))), f, a)
                       for a, f in zip(sampled, fresh)]
            idx = np.nonzero(bad)[0]
            rows = self._padded_rows(idx, b)
            part = self._settle([a[rows] for a in sampled], variations[rows])
            ok[idx] = self.expert_reachable(part)[: len(idx)]
            if ok.all() or attempt == placement_tries - 1:
                env = self._settle(sampled, variations)
        if not ok.all():
            log.warning("%s: %d of %d scenes kept although the expert cannot reach them "
                        "after %d placements", self.task.name, (~ok).sum(), b, placement_tries)
        env.stop_at_success = stop_at_success
        return env

    def _padded_rows(self, idx: np.ndarray, batch: int) -> np.ndarray:
        """Rows to settle again: `idx` itself on native MuJoCo (any batch size runs
        there without compiling), repeated up to the full batch on MJX."""
        return idx if self.backend_name == "native" else np.resize(idx, batch)

    def _settle(self, sampled, variations) -> EnvState:
        qpos, mocap_pos, mocap_quat, rgba = sampled
        b = len(variations)
        m = self.scene.model
        ctrl = np.zeros((b, self.nu))
        ctrl[:, :7] = qpos[:, self.scene.arm_qpos]
        ctrl[:, 7] = FINGER_OPEN
        state = PhysicsState(
            qpos=qpos.astype(np.float64), qvel=np.zeros((b, m.nv)), act=np.zeros((b, m.na)),
            ctrl=ctrl, mocap_pos=mocap_pos.astype(np.float64),
            mocap_quat=mocap_quat.astype(np.float64),
            eq_active=np.tile(m.eq_active0.astype(bool), (b, 1)),
            eq_data=np.tile(m.eq_data, (b, 1, 1)), time=np.zeros(b),
        )
        state, sens = self.backend.run(state, np.repeat(ctrl[:, None], SETTLE_STEPS, axis=1))
        attached = np.zeros((b, len(self.task.graspables)), bool)
        obs = self._obs(np.asarray(sens[:, -1]), attached)
        carry = self._padded(self._jit_init_cond, obs.data, attached, variations)
        return EnvState(
            physics=state.numpy(), obs=obs, carry=carry, variation=variations,
            gripper=np.full(b, FINGER_OPEN), outcome=np.zeros(b, np.int32),
            key_actions=np.zeros(b, np.int32), sim_steps=np.zeros(b, np.int32),
            geom_rgba=rgba, initial_obs=obs,
        )

    def run_expert(self, env: EnvState, record: list[StepResult] | None = None) -> EnvState:
        """Execute the scripted expert until every world is done or out of actions;
        `record`, if given, collects the per-step sensordata of every phase."""
        actions = self.expert_actions(env)
        for k in range(actions.pos.shape[1]):
            step = jax.tree.map(lambda x, k=k: x[:, k], actions)
            if not step.valid.any() or env.done.all():
                break
            env, results = self.step(env, step, record=record is not None)
            if record is not None:
                record.extend(results)
        return env

    def expert_reachable(self, env: EnvState) -> np.ndarray:
        """Whether every expert key action of each world is inside the action
        bounds and solvable by IK (warm-started along the sequence)."""
        actions = self.expert_actions(env)
        q = np.asarray(env.obs.data[:, self._arm_q], np.float64)
        return np.asarray(self._reachable(q, actions.pos, actions.quat, actions.valid))

    def expert_actions(self, env: EnvState) -> KeyActions:
        """The task's scripted expert, computed from the observation at reset."""
        return self._padded(self._jit_expert, env.initial_obs, env.variation)

    def _padded(self, fn, *args):
        """fn(*args) for a batch of any size, run at the reset's batch size (rows
        repeated, results cut back), so re-checking a few rejected scenes reuses the
        programs compiled for the whole batch instead of compiling one per size."""
        n = len(jax.tree.leaves(args)[0])
        size = self._jit_rows or n
        if n >= size:
            return jax.tree.map(np.asarray, fn(*args))
        idx = np.resize(np.arange(n), size)
        out = fn(*jax.tree.map(lambda x: np.asarray(x)[idx], args))
        return jax.tree.map(lambda x: np.asarray(x)[:n], out)

    def _simulate(self, env: EnvState, ctrl: np.ndarray, steps: np.ndarray) -> np.ndarray:
        """Advance world w by its own `steps[w]` physics steps under ctrl[w, :steps[w]] (0: the
        world stays frozen), so a world's timeline never depends on the other worlds in its
        batch, as in RLBench, which runs one episode at a time.  One backend call (MJX: one
        masked scan of the longest move).  Returns sensordata (B, T, S) for T = ctrl.shape[1],
        rows after a world's last step repeating its last row."""
        if self.record_qpos:
            state, sens, self._last_qpos = self.backend.run_with_qpos(env.physics, ctrl, steps)
        else:
            state, sens = self.backend.run(env.physics, ctrl, steps)
        sens = np.array(sens, copy=True)
        frozen = steps == 0
        sens[frozen] = np.asarray(env.obs.data)[frozen][:, None]
        env.physics = state.numpy()
        return sens

    def _run_phase(self, env: EnvState, ctrl: np.ndarray, steps: np.ndarray):
        """Run one phase (world w for steps[w] steps, see _simulate); update conditions,
        outcomes and the latest observation."""
        active = steps > 0
        sens = self._simulate(env, ctrl, steps)
        t = sens.shape[1]
        attached = np.repeat(env.attached[:, None], t, axis=1)
        valid = np.arange(t)[None] < steps[:, None]
        carry, s_idx, f_idx = map(
            lambda x: jax.tree.map(np.asarray, x),
            self._jit_conditions(env.carry, sens, attached, valid, env.variation),
        )
        s_idx, f_idx = np.asarray(s_idx), np.asarray(f_idx)
        # A failure condition ends the episode unless success came first (or at the same
        # step); a success after a failure does not count.
        failed = active & (f_idx >= 0) & ~((s_idx >= 0) & (s_idx <= f_idx))
        succeeded = active & (s_idx >= 0) & ~failed
        stop = succeeded & env.stop_at_success
        end = np.where(stop, s_idx, np.where(failed, f_idx, steps - 1))
        last = sens[np.arange(len(end)), np.maximum(end, 0)]
        data = np.where(active[:, None], last, np.asarray(env.obs.data))
        env.carry = carry
        env.obs = self._obs(data, env.attached)
        env.geom_rgba = self._state_colors.update(env.geom_rgba, env.initial_obs, env.obs,
                                                  env.variation)
        env.sim_steps = env.sim_steps + np.where(active, end + 1, 0).astype(np.int32)
        env.outcome = np.where(succeeded, Outcome.SUCCESS,
                               np.where(failed, Outcome.FAILURE_CONDITION, env.outcome))
        return StepResult(sens, attached, valid & (np.arange(t)[None] <= end[:, None]),
                          self._last_qpos if self.record_qpos else None)

    def step(self, env: EnvState, actions: KeyActions, record: bool = False
             ) -> tuple[EnvState, list[StepResult]]:
        """Execute one key action (arm, then gripper) in every running world.

        `actions` holds one action per world (pos (B,3), quat (B,4), gripper
        (B,), valid (B,)); a world whose action is not valid ends with
        Outcome.NO_ACTION.  On the MJX backends this is one device program
        (key_action.py); `record=True` (the per-step sensor data of every phase, for
        demonstrations) and native MuJoCo take the host path below."""
        if self.on_mjx and not record:
            return self._step_on_device(env, actions), []
        active = ~env.done
        valid = np.asarray(actions.valid, bool)
        running = env.outcome == Outcome.RUNNING
        env.outcome = np.where(active & ~valid & running, Outcome.NO_ACTION, env.outcome)
        active = active & valid
        results: list[StepResult] = []
        if not active.any():
            return env, results

        q0 = np.asarray(env.obs.data[:, self._arm_q], np.float64)
        path, duration, status = map(np.asarray, self._plan(
            q0, np.asarray(actions.pos, q0.dtype), np.asarray(actions.quat, q0.dtype)))
        bad = active & (status != Status.OK)
        for code, outcome in _STATUS_OUTCOME.items():
            env.outcome = np.where(bad & (status == code), outcome, env.outcome)
        active = active & ~bad
        env.key_actions = env.key_actions + active
        if active.any():
            # Arm phase: move, then hold so the arm comes to rest; each world for its own
            # move's (bucketed) length.
            steps = control.bucket_steps(duration + control.SETTLE_TIME, self.dt) * active
            path = np.where(active[:, None, None], path, q0[:, None])
            arm = control.arm_targets(path, np.maximum(duration, 1e-3), int(steps.max()), self.dt)
            ctrl = np.concatenate([arm, np.broadcast_to(env.gripper[:, None, None], (*arm.shape[:2], 1))], -1)
            results.append(self._run_phase(env, ctrl, steps))

        # Gripper phase, only for worlds whose gripper command changes.
        target = np.asarray(control.finger_target(np.asarray(actions.gripper)))
        active = active & ~env.done
        moving = active & (np.abs(target - env.gripper) > 1e-4)
        if moving.any():
            opening = moving & (target > env.gripper)
            self._set_attached(env, env.attached & ~opening[:, None])
            nstep = control.bucket_steps(control.GRIPPER_TIME, self.dt)
            arm_hold = np.asarray(env.physics.ctrl)[:, :7]
            goal = np.where(moving, target, env.gripper)
            grip = control.gripper_targets(env.gripper, goal, nstep, self.dt)
            ctrl = np.concatenate([np.repeat(arm_hold[:, None], nstep, 1), grip[..., None]], -1)
            results.append(self._run_phase(env, ctrl, nstep * moving))
            closing = moving & ~opening & ~env.done
            env.gripper = np.where(moving, target, env.gripper)
            if closing.any() and self.task.graspables:
                hits = np.asarray(self._jit_attach(env.obs.data, env.attached))
                self._set_attached(env, env.attached | (hits & closing[:, None]))

        over = (env.outcome == Outcome.RUNNING) & (env.key_actions >= self.task.max_key_actions)
        env.outcome = np.where(over, Outcome.MAX_STEPS, env.outcome)
        return env, results

    def _step_on_device(self, env: EnvState, actions: KeyActions) -> EnvState:
        """`step` as one device program; the physics state and condition carries stay on
        the device, the host receives the per-world bookkeeping and latest sensor row."""
        from agnostos_mjx.key_action import KeyActionStep, to_device
        from agnostos_mjx.physics.mjx_backend import gc_paused

        dev = to_device(env)
        acts = KeyActions(jnp.asarray(actions.pos, jnp.float32), jnp.asarray(actions.quat, jnp.float32),
                          jnp.asarray(actions.gripper, jnp.float32), jnp.asarray(actions.valid, bool))
        n = len(env.outcome)
        mesh = getattr(self.backend, "mesh", None)
        if mesh is not None:  # worlds split over the local devices (sharding.py)
            (dev, acts), n = sharding.shard((dev, acts), mesh)
        rows = len(dev.outcome)
        if rows not in self._device_steps:
            self._device_steps[rows] = KeyActionStep(self, rows)
        with gc_paused() if self.backend_name == "warp" else contextlib.nullcontext():
            new = jax.block_until_ready(self._device_steps[rows](dev, acts, env.stop_at_success))
        new = sharding.unpad(new, n)
        data, attached, gripper, outcome, key_actions, sim_steps = jax.device_get(
            (new.data, new.attached, new.gripper, new.outcome, new.key_actions, new.sim_steps))
        env.physics, env.carry = new.physics, new.carry
        env.obs = self._obs(np.asarray(data), np.asarray(attached))
        env.gripper, env.outcome = np.asarray(gripper, np.float64), np.asarray(outcome)
        env.key_actions, env.sim_steps = np.asarray(key_actions), np.asarray(sim_steps)
        env.geom_rgba = self._state_colors.update(env.geom_rgba, env.initial_obs, env.obs,
                                                  env.variation)
        return env

    def _set_attached(self, env: EnvState, attached: np.ndarray) -> None:
        """Activate/deactivate grasp welds, freezing the current relative pose."""
        if attached.shape[1] == 0 or np.array_equal(attached, env.attached):
            return
        m = self.scene.model
        newly = attached & ~env.attached
        eq_active = np.array(env.physics.eq_active, bool)
        eq_data = np.array(env.physics.eq_data)
        for w in np.nonzero(newly.any(1))[0]:
            data = posed_data(m, env.physics, w)
            hp, hq = data.xpos[self.scene.hand_body], data.xquat[self.scene.hand_body]
            for g in np.nonzero(newly[w])[0]:
                b = self.scene.graspable_bodies[g]
                rel_p = quat_rotate(quat_conj(hq), data.xpos[b] - hp)
                rel_q = quat_mul(quat_conj(hq), data.xquat[b])
                eq = self.scene.weld_ids[g]
                eq_data[w, eq, :3] = 0.0
                eq_data[w, eq, 3:6] = np.asarray(rel_p)
                eq_data[w, eq, 6:10] = np.asarray(rel_q)
                eq_data[w, eq, 10] = 1.0
        for g, eq in enumerate(self.scene.weld_ids):
            eq_active[:, eq] = attached[:, g]
        env.physics = env.physics.replace(eq_active=eq_active, eq_data=eq_data)
        env.obs = self._obs(env.obs.data, attached)

    def render(self, env: EnvState, camera: str = "front", width: int = 128,
               height: int = 128) -> np.ndarray:
        """RGB frames (B, H, W, 3) of one camera for every world, with each
        world's variation colours (CPU renderer; MJX-warp batch rendering
        comes with the demonstration bank)."""
        from agnostos_mjx.render import CpuRenderer

        if self._renderer is None or (self._renderer.width, self._renderer.height) != (width, height):
            if self._renderer is not None:
                self._renderer.close()
            self._renderer = CpuRenderer(self.scene.model, width, height)
        p = env.physics
        return self._renderer.render(np.asarray(p.qpos), np.asarray(p.mocap_pos),
                                     np.asarray(p.mocap_quat), camera, env.geom_rgba)

    def gripper_open(self, env: EnvState) -> np.ndarray:
        """RLBench's gripper_open flag from the finger opening."""
        return (np.asarray(env.obs["finger_q"])[:, 0] / FINGER_OPEN) > GRIPPER_OPEN_THRESHOLD

    def observe(self, env: EnvState, spec):
        """RLBench-style observation (cameras per `spec`, an observation.ObservationSpec,
        plus proprioception) of every world; see agnostos_mjx/observation.py."""
        from agnostos_mjx.observation import observe

        return observe(self, env, spec)
