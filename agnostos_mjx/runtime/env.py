"""Batched episodes of one task on one physics backend: reset B worlds, execute key actions
for all of them, observe.  Task-agnostic: everything task-specific comes through the
task's sampler, conditions, expert and observables; the key action itself is
runtime/key_action.py over one of runtime/phase.py's boundaries.
"""

from __future__ import annotations

import concurrent.futures
import contextlib
import functools
import logging
from collections.abc import Callable
from typing import TYPE_CHECKING

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
from agnostos_mjx.runtime.planner import PLANNERS, Planner, resolve_planner
from agnostos_mjx.runtime.state import EnvState, StepResult
from agnostos_mjx.runtime.task_fns import TaskFunctions
from agnostos_mjx.sim.control import PandaKinematics
from agnostos_mjx.sim.world import FINGER_OPEN, SceneModel, build_scene
from agnostos_mjx.tasks.base import KeyActions, Task

if TYPE_CHECKING:  # native physics never imports MJX
    from agnostos_mjx.physics.mjx_backend import DevicePhysics

__all__ = ["PLANNERS", "REACH_STEPS", "SETTLE_STEPS", "Episodes", "device_dense_action",
           "device_key_action", "resolve_planner", "sample_and_settle"]

log = logging.getLogger(__name__)
SETTLE_STEPS = 10  # RLBench runs 10 physics steps after placing the scene
REACH_STEPS = 8  # the device planner checks an expert's key actions in multiples of this


def device_key_action(spec: StepSpec, phases: DevicePhases, state: EnvState,
                      actions: KeyActions, plan: tuple) -> EnvState:
    """The key action's new state (a device phase records nothing): what
    `Episodes.device_step` binds to a runner's spec and phases."""
    return key_action(spec, phases, state, actions, plan)[0]


def device_dense_action(spec: StepSpec, phases: DevicePhases, ctl: DenseControl,
                        state: EnvState, targets: KeyActions, plan: tuple) -> EnvState:
    """The dense step's new state, as `device_key_action`."""
    return dense_action(spec, phases, state, targets, plan, ctl)[0]


def sample_and_settle(fns: TaskFunctions, dev: DevicePhysics, stop_at_success: bool,
                      keys: jax.Array, variations: jax.Array) -> EnvState:
    """B worlds sampled and settled (RLBench's 10 steps) in one traceable function: what
    `Episodes.reset` does on the host, without re-sampling the scenes whose expert the arm
    cannot reach (that check is the host's loop)."""
    m, f32 = fns.scene.model, jnp.float32
    variations = jnp.asarray(variations, jnp.int32)
    b = variations.shape[0]
    qpos, mocap_pos, mocap_quat, rgba = jax.vmap(fns.sample, in_axes=(0, 0, None))(
        keys, variations, jnp.int32(0))
    ctrl = jnp.zeros((b, m.nu), f32).at[:, :7].set(qpos[:, fns.scene.arm_qpos])
    ctrl = ctrl.at[:, 7].set(FINGER_OPEN)
    physics = PhysicsState(
        qpos=qpos.astype(f32), qvel=jnp.zeros((b, m.nv), f32), act=jnp.zeros((b, m.na), f32),
        ctrl=ctrl, mocap_pos=mocap_pos.astype(f32), mocap_quat=mocap_quat.astype(f32),
        eq_active=jnp.tile(jnp.asarray(m.eq_active0, bool), (b, 1)),
        eq_data=jnp.tile(jnp.asarray(m.eq_data, f32), (b, 1, 1)), time=jnp.zeros(b, f32))
    model, d = dev.load(physics)

    def settle(_, d):
        return dev.step(model, d, ctrl)

    d = jax.lax.fori_loop(0, SETTLE_STEPS, settle, d)
    data = d.sensordata
    attached = jnp.zeros((b, len(fns.task.graspables)), bool)
    carry, _ = jax.vmap(fns.settled)(data, attached, variations)
    zeros = jnp.zeros(b, jnp.int32)
    return EnvState(
        physics=dev.save(physics, d), data=data, attached=attached, carry=carry,
        variation=variations, gripper=jnp.full(b, FINGER_OPEN, f32), outcome=zeros,
        key_actions=zeros, sim_steps=zeros, world_steps=zeros, geom_rgba=rgba,
        initial_data=data, layout=fns.scene.layout, stop_at_success=stop_at_success)


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
        self.fns = TaskFunctions.of(task, self.scene)
        self.observer = Observer(task, self.scene, self.backend_name, renderer)
        # Every jitted program of this runner, by (kind, batch, ...): reset's (the placement;
        # one program for a settled scene's first condition carry and expert), the host's
        # condition scan and grasp test here, the device's key action and dense step as
        # their batches come (device_program, dense_program).
        self.programs: dict[tuple, Callable] = {
            ("sample",): jax.jit(jax.vmap(self.fns.sample, in_axes=(0, 0, None))),
            ("settled",): jax.jit(jax.vmap(self.fns.settled)),
            ("conditions",): jax.jit(jax.vmap(scan_conditions(self.fns.condition_step))),
        }
        if task.graspables:
            self.programs[("attach",)] = jax.jit(jax.vmap(self.fns.attach))
        self.spec = StepSpec(
            arm_q=self.scene.layout.slice("arm_q"), dt=self.dt,
            max_key_actions=task.max_key_actions, condition_step=self.fns.condition_step,
            attach=self.programs.get(("attach",)), hand_body=self.scene.hand_body,
            graspable_bodies=self.scene.graspable_bodies, weld_ids=self.scene.weld_ids,
            repaint=self.fns.colors)
        # Next to host physics, planning (IK and the Cartesian path of every world) is one
        # compiled program shared by every task of a run (control.jit_for_robot) wherever
        # there is an accelerator; on a CPU-only machine it is plain numpy (float64), which
        # is faster there and what the recorded results were made with (resolve_planner).
        # Next to MJX the plan is always the shared program (`device_plans`).
        self.planner = resolve_planner(planner)
        self.plans = Planner.chosen(self.kin, planner)
        self.device_plans = Planner.device(self.kin)
        self._jit_rows: int | None = None  # batch the jitted reset helpers run at

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
        sampled = list(map(np.asarray, self.programs[("sample",)](keys, variations, np.int32(0))))
        state, expert = self._settle(sampled, variations)
        ok = np.array(self.expert_reachable(state, expert), copy=True)
        for attempt in range(1, placement_tries):
            if ok.all():
                break
            # Only the rejected scenes are settled and checked again (in a padded batch,
            # so jitted shapes stay few); every world is settled once more at the end.
            fresh = list(map(np.asarray, self.programs[("sample",)](keys, variations, np.int32(attempt))))
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
        carry, expert = self._padded(self.programs[("settled",)], data, attached, variations)
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
        if not self.plans.on_device:
            return np.asarray(self.plans.reachable(q, actions.pos, actions.quat, actions.valid))
        # The jitted check runs at the reset's batch size and at a multiple of REACH_STEPS key
        # actions (an invalid one changes nothing): one program for a task's resets and
        # re-samples, and a few for a run's tasks, where each size compiled one.
        pad = ((0, 0), (0, -actions.pos.shape[1] % REACH_STEPS))
        quat = np.pad(np.asarray(actions.quat), (*pad, (0, 0)))
        quat[:, actions.pos.shape[1]:, 0] = 1.0
        return self._padded(self.plans.reachable, q, np.pad(np.asarray(actions.pos), (*pad, (0, 0))),
                            quat, np.pad(np.asarray(actions.valid), pad), rows=self.plan_rows)

    def expert_actions(self, state: EnvState) -> KeyActions:
        """The task's scripted expert, computed from the observation at reset."""
        initial = state.initial_obs
        return self._padded(self.programs[("settled",)], initial.data, initial.attached,
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
        if plan is None:
            plan = self._plan_on_host(self.plans.plan, state, actions)
        phases = self._host_phases()
        with jax.default_device(host_device()):
            return key_action(self.spec, phases, state, jax.tree.map(np.asarray, actions),
                              tuple(map(np.asarray, plan)))

    def plan_request(self, state: EnvState, actions: KeyActions
                     ) -> concurrent.futures.Future | None:
        """The plan of `step` on the host as a request that gathers with other tasks' (one
        device planner call for the worlds of every task waiting: runtime/plan_rows.py);
        None where `step` plans by itself (the host planner, the MJX backends)."""
        if self.capabilities.on_device or not self.plans.on_device:
            return None
        q0 = np.asarray(state.data[:, self.spec.arm_q], np.float64)
        return GatheredPlanner.for_robot(self.kin).submit(q0, actions.pos, actions.quat,
                                                          self.plan_rows)

    def _host_phases(self, rows: int = CONDITION_ROWS) -> HostPhases:
        """The host's physics boundary (numpy; its jitted helpers on the CPU); `rows`: the
        condition program's rows per call."""
        return HostPhases(self.backend, self.scene.model, self.programs[("conditions",)],
                          self.record_qpos, rows)

    def _plan_on_host(self, plan_fn: Callable, state: EnvState, actions: KeyActions) -> tuple:
        """`plan_fn(q, pos, quat)` from the current joints, in float64, as numpy: asked
        before the key action, on JAX's default device (the device planner's)."""
        q0 = np.asarray(state.data[:, self.spec.arm_q], np.float64)
        return tuple(map(np.asarray, plan_fn(
            q0, np.asarray(actions.pos, q0.dtype), np.asarray(actions.quat, q0.dtype))))

    def step_on_device(self, state: EnvState, actions: KeyActions, physics=None,
                       unroll: int | None = None) -> EnvState:
        """`step` as one device program; the physics state and condition carries stay on
        the device, the host receives the per-world bookkeeping and latest sensor row.
        `physics`, `unroll`: see `device_step`."""
        dev, acts, n = self._to_device(state, actions)
        program = self.device_program(dev.batch, physics, unroll)
        # The plan is its own program, shared by every task (control.jit_for_robot): the
        # IK is most of the compile time, and the robot is the same in every scene.
        plan = self.device_plans.plan(dev.data[:, self.spec.arm_q], acts.pos, acts.quat)
        return self._run_program(program, dev, acts, plan, n)

    def _to_device(self, state: EnvState, actions: KeyActions
                   ) -> tuple[EnvState, KeyActions, int]:
        """State and actions as JAX arrays, split over the local devices where the backend
        has several (sharding.py); with the batch to cut the result back to."""
        dev = state.to_device()
        acts = KeyActions(jnp.asarray(actions.pos, jnp.float32),
                          jnp.asarray(actions.quat, jnp.float32),
                          jnp.asarray(actions.gripper, jnp.float32),
                          jnp.asarray(actions.valid, bool))
        n = state.batch
        mesh = getattr(self.backend, "mesh", None)
        if mesh is not None:  # worlds split over the local devices (sharding.py)
            (dev, acts), n = sharding.shard((dev, acts), mesh)
        return dev, acts, n

    def _run_program(self, program: Callable, dev: EnvState, acts: KeyActions, plan: tuple,
                     n: int) -> EnvState:
        """`program(dev, acts, plan)` to its end; the host's view of its first `n` worlds."""
        from agnostos_mjx.infra.gc_pause import gc_paused

        with gc_paused() if self.capabilities.captures_graphs else contextlib.nullcontext():
            new = jax.block_until_ready(program(dev, acts, plan))
        return sharding.unpad(new, n).to_host()

    def device_step(self, batch: int, physics=None, unroll: int | None = None
                    ) -> Callable[[EnvState, KeyActions, tuple], EnvState]:
        """The key action of `batch` worlds on the device as a pure function (state,
        actions, plan) -> state over JAX arrays (`EnvState.to_device`; the plan
        `self.device_plans.plan(q, pos, quat)`): jit it, or trace it into a program of
        your own.  `physics`: the DevicePhysics to step (default: this runner's MJX
        backend's); `unroll`: physics steps per loop iteration (default:
        phase.steps_per_iteration)."""
        dev = physics or self.backend.device_physics(batch)
        phases = DevicePhases(dev, self.spec.condition_step,
                              unroll or steps_per_iteration(self.backend_name))
        return functools.partial(device_key_action, self.spec, phases)

    def device_reset(self, batch: int, stop_at_success: bool = True, physics=None
                     ) -> Callable[[jax.Array, jax.Array], EnvState]:
        """Reset of `batch` worlds on the device as a pure function (keys, variations) ->
        state (`sample_and_settle`: no re-sampling of scenes the expert cannot reach);
        `physics` as in `device_step`."""
        return functools.partial(sample_and_settle, self.fns,
                                 physics or self.backend.device_physics(batch), stop_at_success)

    def device_program(self, batch: int, physics=None, unroll: int | None = None) -> Callable:
        """`device_step` jitted, compiled once per batch size (and per stop_at_success)."""
        key = ("key_action", batch, physics, unroll)
        if key not in self.programs:
            self.programs[key] = jax.jit(self.device_step(batch, physics, unroll))
        return self.programs[key]

    # ---- one dense control step ---------------------------------------------------------
    def step_dense(self, state: EnvState, targets: KeyActions, ctl: DenseControl,
                   record: bool = False) -> tuple[EnvState, tuple[StepResult, ...]]:
        """Execute one control period (runtime/dense.py) toward each world's target:
        pos (B, 3) tip position, quat (B, 4) wxyz, gripper (B,) open amount, valid (B,).
        On the MJX backends one device program (unless `record`); native MuJoCo and
        `record=True` run the same step on the host."""
        if self.capabilities.on_device and not record:
            return self.dense_on_device(state, targets, ctl), ()
        plan = self._plan_on_host(self.plans.dense_ik, state, targets)
        phases = self._host_phases(condition_rows(ctl.period_steps))
        with jax.default_device(host_device()):
            return dense_action(self.spec, phases, state, jax.tree.map(np.asarray, targets),
                                plan, ctl)

    def dense_on_device(self, state: EnvState, targets: KeyActions, ctl: DenseControl,
                        physics=None) -> EnvState:
        """`step_dense` as one device program (the IK its own program, shared by every
        task as the key action's plan is); `physics`: the DevicePhysics to step (default:
        this runner's MJX backend's)."""
        dev, acts, n = self._to_device(state, targets)
        program = self.dense_program(dev.batch, ctl, physics)
        plan = self.device_plans.dense_ik(dev.data[:, self.spec.arm_q], acts.pos, acts.quat)
        return self._run_program(program, dev, acts, plan, n)

    def dense_step(self, batch: int, ctl: DenseControl, physics=None
                   ) -> Callable[[EnvState, KeyActions, tuple], EnvState]:
        """The dense step of `batch` worlds as a pure function (state, targets, IK plan)
        -> state, as `device_step` (the plan `self.device_plans.dense_ik(q, pos, quat)`)."""
        phases = DevicePhases(physics or self.backend.device_physics(batch),
                              self.spec.condition_step, steps_per_iteration(self.backend_name))
        return functools.partial(device_dense_action, self.spec, phases, ctl)

    def dense_program(self, batch: int, ctl: DenseControl, physics=None) -> Callable:
        """`dense_step` jitted, compiled once per batch size and control."""
        key = ("dense", batch, ctl, physics)
        if key not in self.programs:
            self.programs[key] = jax.jit(self.dense_step(batch, ctl, physics))
        return self.programs[key]

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
