"""Batched episodes of one task on one physics backend: reset B worlds, execute key actions
for all of them, observe.  Task-agnostic: everything task-specific comes through the
task's sampler, conditions, expert and observables; the key action itself is
runtime/key_action.py over one of runtime/phase.py's boundaries.
"""

from __future__ import annotations

import concurrent.futures
import contextlib
import logging

import jax
import jax.numpy as jnp
import numpy as np

from agnostos_mjx.infra import sharding
from agnostos_mjx.physics import make_backend, resolve_backend
from agnostos_mjx.physics.base import PhysicsState
from agnostos_mjx.runtime.dense import DenseControl, dense_action
from agnostos_mjx.runtime.key_action import StepSpec, key_action
from agnostos_mjx.runtime.observe import Observer
from agnostos_mjx.runtime.phase import (
    CONDITION_ROWS,
    DevicePhases,
    HostPhases,
    condition_rows,
    host_device,
    scan_conditions,
    steps_per_iteration,
)
from agnostos_mjx.runtime.plan_rows import GatheredPlanner
from agnostos_mjx.runtime.state import EnvState, StepResult
from agnostos_mjx.sim import control
from agnostos_mjx.sim.control import PandaKinematics
from agnostos_mjx.sim.math3d import quat_conj, quat_rotate
from agnostos_mjx.sim.observables import Observation
from agnostos_mjx.sim.visual_state import StateColors
from agnostos_mjx.sim.world import FINGER_OPEN, SceneModel, apply_placement, build_scene
from agnostos_mjx.tasks.base import KeyActions, Task

log = logging.getLogger(__name__)
SETTLE_STEPS = 10  # RLBench runs 10 physics steps after placing the scene
# Attach volume between the fingers in the tip frame (RLBench's attach proximity
# sensor: 0.02 x 0.10 m face, 0.045 m deep along the approach axis).
ATTACH_CENTER = np.array([0.0, 0.0, -0.018])
ATTACH_HALF = np.array([0.01, 0.05, 0.0275])


PLANNERS = ("auto", "host", "device")


REACH_STEPS = 8  # the device planner checks an expert's key actions in multiples of this


def resolve_planner(name: str) -> str:
    """`auto`: `device` when JAX has an accelerator, else `host`.  `device`: the jitted
    float32 planner (one program for every task, off the host's Python loop); `host`: numpy
    float64 (the CPU path, bit for bit as before).  The two can pick different IK
    solutions near a limit, so a run's records say which (`Episodes.planner`)."""
    if name not in PLANNERS:
        raise ValueError(f"unknown planner {name!r}; choose one of {', '.join(PLANNERS)}")
    if name == "auto":
        return "device" if jax.default_backend() != "cpu" else "host"
    return name


class Episodes:
    """Runs batches of episodes of one task on one backend."""

    # Recorded phases carry each step's qpos (native backend only), to render in-between
    # frames of demonstrations.
    record_qpos: bool = False

    def __init__(self, task: Task, backend: str = "auto", threads: int | None = None,
                 planner: str = "auto", plan_rows: int | None = None, renderer: str = "auto"):
        """`plan_rows`: the rows the device planner's programs run at, fewer worlds padded
        (an evaluation's --batch): a world's float32 plan moves with its program's shape,
        so the worlds of a task plan alike whether its seeds run in one batch or apart.
        `renderer`: where observations render (physics.RENDERERS; auto: the machine's)."""
        self.task = task
        self.plan_rows = plan_rows
        self.scene: SceneModel = build_scene(task)
        self.backend_name = resolve_backend(backend)
        self.backend = make_backend(self.backend_name, self.scene.model, threads)
        self.capabilities = self.backend.capabilities
        self.kin = PandaKinematics.from_model(self.scene.model)
        self.dt = float(self.scene.model.opt.timestep)
        self.nu = self.scene.model.nu
        self.state_colors = StateColors(task, self.scene.model, self.scene.layout)
        self.observer = Observer(task, self.scene, self.backend_name, renderer)
        self.spec = StepSpec(
            arm_q=self.scene.layout.slice("arm_q"), dt=self.dt,
            max_key_actions=task.max_key_actions, condition_step=self._condition_step,
            attach=jax.jit(jax.vmap(self._attach_test)) if task.graspables else None,
            hand_body=self.scene.hand_body, graspable_bodies=self.scene.graspable_bodies,
            weld_ids=self.scene.weld_ids, repaint=self.state_colors)
        self._jit_sample = jax.jit(jax.vmap(self._sample_one, in_axes=(0, 0, None)))
        # One program for what a settled scene gives: its conditions' first carry and the
        # expert's key actions (reset rejects scenes the expert cannot reach).
        self._jit_settled = jax.jit(jax.vmap(self._settled_one))
        self._jit_conditions = jax.jit(jax.vmap(scan_conditions(self._condition_step)))
        # Planning (IK and the Cartesian path of every world) is one compiled program shared
        # by every task of a run (control.jit_for_robot) wherever there is an accelerator,
        # for native MuJoCo too; on a CPU-only machine it is plain numpy (float64), which
        # is faster there and what the recorded results were made with (see resolve_planner).
        self.planner = resolve_planner(planner)
        on_device = self.planner == "device"
        self._device_plan = control.jit_for_robot(control.plan_arm, self.kin)
        self._plan = self._device_plan if on_device else (
            lambda q, p, r: control.plan_arm(self.kin, q, p, r))
        self._reachable = control.jit_for_robot(control.reachable, self.kin) if on_device else (
            lambda *args: control.reachable(self.kin, *args))
        self._device_programs: dict = {}  # batch size -> jitted key action (compiled once each)
        # Dense control's IK (runtime/dense.py): one small descent per control step, which
        # native physics runs on the host (a device call's round trip costs more than the
        # numpy IK) unless the device planner is asked for by name.
        self._dense_ik = control.jit_for_robot(control.dense_ik, self.kin)
        self._dense_plan = self._dense_ik if planner == "device" else (
            lambda q, p, r: control.dense_ik(self.kin, q, p, r))
        self._jit_rows: int | None = None  # batch the jitted reset helpers run at

    # ---- pure pieces (vmapped above) -------------------------------------------------
    def _sample_one(self, key, variation, attempt):
        """A placement; attempt k > 0 draws from fold_in(key, k) (reset's re-sampling)."""
        key = jnp.where(attempt > 0, jax.random.fold_in(key, attempt), key)
        return apply_placement(self.scene, self.task.sample(key, variation))

    def _obs(self, data, attached) -> Observation:
        return Observation(data, self.scene.layout, attached)

    def _settled_one(self, data, attached, variation):
        """(the success and failure trees' first carry, the expert's key actions)."""
        obs = self._obs(data, attached)
        carry = (self.task.success(variation).init(obs), self.task.failure(variation).init(obs))
        return carry, self.task.expert(obs, variation)

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

    # ---- reset ------------------------------------------------------------------------
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
        sampled = list(map(np.asarray, self._jit_sample(keys, variations, np.int32(0))))
        state, expert = self._settle(sampled, variations)
        ok = np.array(self.expert_reachable(state, expert), copy=True)
        for attempt in range(1, placement_tries):
            if ok.all():
                break
            # Only the rejected scenes are settled and checked again (in a padded batch,
            # so jitted shapes stay few); every world is settled once more at the end.
            fresh = list(map(np.asarray, self._jit_sample(keys, variations, np.int32(attempt))))
            bad = ~ok
            sampled = [np.where(bad.reshape(-1, *([1] * (a.ndim - 1))), f, a)
                       for a, f in zip(sampled, fresh)]
            idx = np.nonzero(bad)[0]
            rows = self._padded_rows(idx, b)
            part, expert = self._settle([a[rows] for a in sampled], variations[rows])
            ok[idx] = self.expert_reachable(part, expert)[: len(idx)]
            if ok.all() or attempt == placement_tries - 1:
                state, _ = self._settle(sampled, variations)
        if not ok.all():
            log.warning("%s: %d of %d scenes kept although the expert cannot reach them "
                        "after %d placements", self.task.name, (~ok).sum(), b, placement_tries)
        return state.replace(stop_at_success=stop_at_success)

    def _padded_rows(self, idx: np.ndarray, batch: int) -> np.ndarray:
        """Rows to settle again: `idx` itself on native MuJoCo (any batch size runs
        there without compiling), repeated up to the full batch on MJX."""
        return np.resize(idx, batch) if self.capabilities.padded_batch else idx

    def _settle(self, sampled, variations) -> tuple[EnvState, KeyActions]:
        """The settled scenes of `sampled` placements, and their experts' key actions (one
        program gives both, with the conditions' first carry)."""
        qpos, mocap_pos, mocap_quat, rgba = sampled
        b = len(variations)
        m = self.scene.model
        ctrl = np.zeros((b, self.nu))
        ctrl[:, :7] = qpos[:, self.scene.arm_qpos]
        ctrl[:, 7] = FINGER_OPEN
        physics = PhysicsState(
            qpos=qpos.astype(np.float64), qvel=np.zeros((b, m.nv)), act=np.zeros((b, m.na)),
            ctrl=ctrl, mocap_pos=mocap_pos.astype(np.float64),
            mocap_quat=mocap_quat.astype(np.float64),
            eq_active=np.tile(m.eq_active0.astype(bool), (b, 1)),
            eq_data=np.tile(m.eq_data, (b, 1, 1)), time=np.zeros(b),
        )
        physics, sens = self.backend.run(physics, np.repeat(ctrl[:, None], SETTLE_STEPS, axis=1))
        attached = np.zeros((b, len(self.task.graspables)), bool)
        data = np.asarray(sens[:, -1])
        carry, expert = self._padded(self._jit_settled, data, attached, variations)
        return EnvState(
            physics=physics.numpy(), data=data, attached=attached, carry=carry,
            variation=variations, gripper=np.full(b, FINGER_OPEN),
            outcome=np.zeros(b, np.int32), key_actions=np.zeros(b, np.int32),
            sim_steps=np.zeros(b, np.int32), world_steps=np.zeros(b, np.int32),
            geom_rgba=rgba, initial_data=data,
            layout=self.scene.layout), expert

    # ---- the expert ---------------------------------------------------------------------
    def run_expert(self, state: EnvState, record: list[StepResult] | None = None) -> EnvState:
        """Execute the scripted expert until every world is done or out of actions;
        `record`, if given, collects the per-step sensordata of every phase."""
        actions = self.expert_actions(state)
        for k in range(actions.pos.shape[1]):
            step = jax.tree.map(lambda x, k=k: x[:, k], actions)
            if not step.valid.any() or state.done.all():
                break
            state, results = self.step(state, step, record=record is not None)
            if record is not None:
                record.extend(results)
        return state

    def expert_reachable(self, state: EnvState, actions: KeyActions | None = None
                         ) -> np.ndarray:
        """Whether every expert key action of each world is inside the action
        bounds and solvable by IK (warm-started along the sequence); `actions`: the
        experts' key actions when the caller has them (reset does)."""
        actions = self.expert_actions(state) if actions is None else actions
        q = np.asarray(state.data[:, self.spec.arm_q], np.float64)
        if self.planner != "device":
            return np.asarray(self._reachable(q, actions.pos, actions.quat, actions.valid))
        # The jitted check runs at the reset's batch size and at a multiple of REACH_STEPS key
        # actions (an invalid one changes nothing): one program for a task's resets and
        # re-samples, and a few for a run's tasks, where each size compiled one.
        pad = ((0, 0), (0, -actions.pos.shape[1] % REACH_STEPS))
        quat = np.pad(np.asarray(actions.quat), (*pad, (0, 0)))
        quat[:, actions.pos.shape[1]:, 0] = 1.0
        return self._padded(self._reachable, q, np.pad(np.asarray(actions.pos), (*pad, (0, 0))),
                            quat, np.pad(np.asarray(actions.valid), pad), rows=self.plan_rows)

    def expert_actions(self, state: EnvState) -> KeyActions:
        """The task's scripted expert, computed from the observation at reset."""
        initial = state.initial_obs
        return self._padded(self._jit_settled, initial.data, initial.attached,
                            state.variation)[1]

    def _padded(self, fn, *args, rows: int | None = None):
        """fn(*args) for a batch of any size, run at the reset's batch size, at least `rows`
        (rows repeated, results cut back), so re-checking a few rejected scenes reuses the
        programs compiled for the whole batch instead of compiling one per size."""
        n = len(jax.tree.leaves(args)[0])
        size = max(self._jit_rows or n, rows or 0)
        if n >= size:
            return jax.tree.map(np.asarray, fn(*args))
        idx = np.resize(np.arange(n), size)
        out = fn(*jax.tree.map(lambda x: np.asarray(x)[idx], args))
        return jax.tree.map(lambda x: np.asarray(x)[:n], out)

    # ---- one key action -----------------------------------------------------------------
    def step(self, state: EnvState, actions: KeyActions, record: bool = False,
             plan: tuple | None = None) -> tuple[EnvState, tuple[StepResult, ...]]:
        """Execute one key action (arm, then gripper) in every running world.

        `actions` holds one action per world (pos (B,3), quat (B,4), gripper
        (B,), valid (B,)); a world whose action is not valid ends with
        Outcome.NO_ACTION.  On the MJX backends this is one device program;
        `record=True` (the per-step sensor data of every phase, for demonstrations)
        and native MuJoCo run the same key action on the host, with `plan` (from
        `plan_request`) when the caller has it."""
        if self.capabilities.on_device and not record:
            return self.step_on_device(state, actions), ()
        plan_fn = self._plan if plan is None else (lambda *_: plan)
        return self._run_on_host(state, actions, plan_fn,
                                 lambda *args: key_action(self.spec, *args))

    def plan_request(self, state: EnvState, actions: KeyActions
                     ) -> concurrent.futures.Future | None:
        """The plan of `step` on the host as a request that gathers with other tasks' (one
        device planner call for the worlds of every task waiting: runtime/plan_rows.py);
        None where `step` plans by itself (the host planner, the MJX backends)."""
        if self.capabilities.on_device or self.planner != "device":
            return None
        q0 = np.asarray(state.data[:, self.spec.arm_q], np.float64)
        return GatheredPlanner.for_robot(self.kin).submit(q0, actions.pos, actions.quat,
                                                          self.plan_rows)

    def _run_on_host(self, state: EnvState, actions: KeyActions, plan_fn, run,
                     rows: int = CONDITION_ROWS) -> tuple[EnvState, tuple[StepResult, ...]]:
        """`run(phases, state, actions, plan)` on the host (HostPhases, numpy; its jitted
        helpers on the CPU), the plan `plan_fn(q, pos, quat)` from the current joints;
        `rows`: the condition program's rows per call."""
        phases = HostPhases(self.backend, self.scene.model, self._jit_conditions,
                            self.record_qpos, rows)
        q0 = np.asarray(state.data[:, self.spec.arm_q], np.float64)
        plan = tuple(map(np.asarray, plan_fn(
            q0, np.asarray(actions.pos, q0.dtype), np.asarray(actions.quat, q0.dtype))))
        actions = jax.tree.map(np.asarray, actions)
        with jax.default_device(host_device()):
            return run(phases, state, actions, plan)

    def step_on_device(self, state: EnvState, actions: KeyActions, physics=None,
                       unroll: int | None = None) -> EnvState:
        """`step` as one device program; the physics state and condition carries stay on
        the device, the host receives the per-world bookkeeping and latest sensor row.
        `physics`, `unroll`: see `device_program`."""
        return self._run_on_device(state, actions,
                                   lambda b: self.device_program(b, physics, unroll),
                                   self._device_plan)

    def _run_on_device(self, state: EnvState, actions: KeyActions, program_for, plan_fn
                       ) -> EnvState:
        """`program_for(batch)(state, actions, plan_fn(q, pos, quat))` with state and
        actions as JAX arrays, split over the local devices where the backend has several
        (sharding.py); returns the host's view of the new state."""
        from agnostos_mjx.physics.mjx_backend import gc_paused

        dev = state.to_device()
        acts = KeyActions(jnp.asarray(actions.pos, jnp.float32),
                          jnp.asarray(actions.quat, jnp.float32),
                          jnp.asarray(actions.gripper, jnp.float32),
                          jnp.asarray(actions.valid, bool))
        n = state.batch
        mesh = getattr(self.backend, "mesh", None)
        if mesh is not None:  # worlds split over the local devices (sharding.py)
            (dev, acts), n = sharding.shard((dev, acts), mesh)
        program = program_for(dev.batch)
        # The plan is its own program, shared by every task (control.jit_for_robot): the
        # IK is most of the compile time, and the robot is the same in every scene.
        plan = plan_fn(dev.data[:, self.spec.arm_q], acts.pos, acts.quat)
        with gc_paused() if self.capabilities.captures_graphs else contextlib.nullcontext():
            new = jax.block_until_ready(program(dev, acts, plan))
        return sharding.unpad(new, n).to_host()

    def device_program(self, batch: int, physics=None, unroll: int | None = None):
        """The jitted key action of a batch of `batch` worlds: (state, actions, plan) ->
        state, compiled once per batch size (and per stop_at_success).  `physics`: the
        DevicePhysics to step (default: this runner's MJX backend's); `unroll`: physics
        steps per loop iteration (default: phase.steps_per_iteration)."""
        key = (batch, physics, unroll)
        if key not in self._device_programs:
            dev = physics or self.backend.device_physics(batch)
            k = unroll or steps_per_iteration(self.backend_name)
            phases = DevicePhases(dev, self._condition_step, k)
            self._device_programs[key] = jax.jit(
                lambda s, a, p: key_action(self.spec, phases, s, a, p)[0])
        return self._device_programs[key]

    # ---- one dense control step ---------------------------------------------------------
    def step_dense(self, state: EnvState, targets: KeyActions, ctl: DenseControl,
                   record: bool = False) -> tuple[EnvState, tuple[StepResult, ...]]:
        """Execute one control period (runtime/dense.py) toward each world's target:
        pos (B, 3) tip position, quat (B, 4) wxyz, gripper (B,) open amount, valid (B,).
        On the MJX backends one device program (unless `record`); native MuJoCo and
        `record=True` run the same step on the host."""
        if self.capabilities.on_device and not record:
            return self.dense_on_device(state, targets, ctl), ()
        return self._run_on_host(state, targets, self._dense_plan,
                                 lambda *args: dense_action(self.spec, *args, ctl),
                                 condition_rows(ctl.period_steps))

    def dense_on_device(self, state: EnvState, targets: KeyActions, ctl: DenseControl,
                        physics=None) -> EnvState:
        """`step_dense` as one device program (the IK its own program, shared by every
        task as the key action's plan is); `physics`: the DevicePhysics to step (default:
        this runner's MJX backend's)."""
        return self._run_on_device(state, targets,
                                   lambda b: self.dense_program(b, ctl, physics),
                                   self._dense_ik)

    def dense_program(self, batch: int, ctl: DenseControl, physics=None):
        """The jitted dense step of `batch` worlds: (state, targets, IK plan) -> state,
        compiled once per batch size and control (as `device_program`)."""
        key = ("dense", batch, ctl, physics)
        if key not in self._device_programs:
            phases = DevicePhases(physics or self.backend.device_physics(batch),
                                  self._condition_step, steps_per_iteration(self.backend_name))
            self._device_programs[key] = jax.jit(
                lambda s, a, p: dense_action(self.spec, phases, s, a, p, ctl)[0])
        return self._device_programs[key]

    # ---- observation ------------------------------------------------------------------
    def render(self, state: EnvState, camera: str = "front", width: int = 128,
               height: int = 128, worlds: np.ndarray | None = None) -> np.ndarray:
        """RGB frames (B, H, W, 3) of one camera for every world (or the `worlds` given),
        with each world's colours (CPU renderer)."""
        return self.observer.render(state, camera, width, height, worlds)

    def gripper_open(self, state: EnvState) -> np.ndarray:
        """RLBench's gripper_open flag from the finger opening."""
        return self.observer.gripper_open(state)

    def observe(self, state: EnvState, spec):
        """RLBench-style observation (cameras per `spec`, an observation.ObservationSpec,
        plus proprioception) of every world; see agnostos_mjx/runtime/observation.py."""
        return self.observer.observe(state, spec)

    def close(self) -> None:
        """Free the renderers (GL contexts, device buffers) this runner created."""
        self.observer.close()
