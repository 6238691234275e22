"""The hot path on the MJX backends: one key action for B worlds as one device program.

    plan (IK with restarts, Cartesian or joint path: one program shared by all tasks)
    ->  arm phase  ->  gripper phase
    each phase: a `lax.while_loop` over physics steps; after every step the task's success
    and failure conditions; a world is frozen past its own end, at a failure, or at its
    success, and the loop stops when no world is left moving (not after the longest move)
    ->  grasp attach (RLBench's proximity test, weld poses from the kinematics)

Per-world step counts are data, never shapes, so the program is compiled once per (task,
batch size) and no batch re-runs per bucket of move lengths.  The host sends the key
actions and receives the per-world bookkeeping and latest sensor row; the physics state
and the condition carries stay on the device between key actions.

Semantics are those of the host path in episode.py (which records every step and runs on
native MuJoCo): same plan, same per-world timelines (control.bucket_steps), same condition
order (a success at or before a failure wins).  The one difference: a world that finished
mid-phase keeps its state at that step here, where the host path steps it to the phase's
end; the episode is over either way, and its final observation is the same.
"""

from __future__ import annotations

import dataclasses
import os
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import jax
import jax.numpy as jnp
import numpy as np

from agnostos_mjx import control
from agnostos_mjx.math3d import quat_conj, quat_mul, quat_rotate
from agnostos_mjx.physics.base import PhysicsState
from agnostos_mjx.physics.mjx_backend import DevicePhysics, freeze, keep_rows
from agnostos_mjx.tasks.base import KeyActions

if TYPE_CHECKING:
    from agnostos_mjx.episode import Episodes


@jax.tree_util.register_dataclass
@dataclass
class DeviceEnv:
    """What a key action reads and changes, per world (leading axis B)."""

    physics: PhysicsState
    data: jax.Array  # latest sensor row (B, nsensordata)
    attached: jax.Array  # (B, ngraspable) grasp welds on
    carry: Any  # (success, failure) condition carries
    variation: jax.Array
    gripper: jax.Array  # commanded finger position
    outcome: jax.Array
    key_actions: jax.Array
    sim_steps: jax.Array

    def replace(self, **changes: Any) -> DeviceEnv:
        return dataclasses.replace(self, **changes)


def steps_per_iteration(backend_name: str) -> int:
    """Physics steps per iteration of a phase's while loop.

    Each iteration ends with the host reading the loop's condition from the device, so the
    host cannot queue the next step before the device has finished this one: on MJX-Warp,
    whose step is a Python FFI callback (~1 ms of host time for ~1 ms of GPU time at batch
    75), host and device then take turns instead of overlapping.  Unrolling a few steps
    lets them overlap; on MJX-jax a step is a large program, and unrolling would multiply
    its compile time.  ``AGNOSTOS_STEPS_PER_ITERATION`` overrides it (measurements)."""
    override = os.environ.get("AGNOSTOS_STEPS_PER_ITERATION")
    if override:
        return max(1, int(override))
    return 4 if backend_name == "warp" else 1


class KeyActionStep:
    """`KeyActionStep(episodes, batch)(env, actions) -> env` for an MJX backend."""

    def __init__(self, episodes: Episodes, batch: int):
        from agnostos_mjx.episode import _STATUS_OUTCOME, Outcome

        self.ep = episodes
        self.outcome = Outcome
        self.status_outcome = _STATUS_OUTCOME
        self.dev: DevicePhysics = episodes.backend.device_physics(batch)
        self.gripper_steps = control.bucket_steps(control.GRIPPER_TIME, episodes.dt)
        self.steps_per_iteration = steps_per_iteration(episodes.backend_name)
        self._program = jax.jit(self._key_action, static_argnames="stop_at_success")

    def __call__(self, env: DeviceEnv, actions: KeyActions, stop_at_success: bool) -> DeviceEnv:
        # The plan is its own program, shared by every task (control.jit_for_robot): the IK
        # is most of the compile time, and the robot is the same in every scene.
        plan = self.ep._device_plan(env.data[:, self.ep._arm_q], actions.pos, actions.quat)
        return self._program(env, actions, plan, stop_at_success=stop_at_success)

    # ---- the program ------------------------------------------------------------------
    def _key_action(self, env: DeviceEnv, actions: KeyActions, plan: tuple,
                    stop_at_success: bool) -> DeviceEnv:
        ep, out = self.ep, self.outcome
        running = env.outcome == out.RUNNING
        done = self._done(env.outcome, stop_at_success)
        valid = jnp.asarray(actions.valid, bool)
        outcome = jnp.where(~done & ~valid & running, out.NO_ACTION, env.outcome)
        active = ~done & valid

        q0 = env.data[:, ep._arm_q]
        path, duration, status = plan
        bad = active & (status != control.Status.OK)
        for code, reason in self.status_outcome.items():
            outcome = jnp.where(bad & (status == code), reason, outcome)
        active = active & ~bad
        env = env.replace(outcome=outcome, key_actions=env.key_actions + active)

        # Arm phase: move along the path, then hold so the arm comes to rest.
        steps = control.bucket_steps(duration + control.SETTLE_TIME, ep.dt) * active
        duration = jnp.maximum(duration, 1e-3)
        dt = jnp.asarray(ep.dt, q0.dtype)

        def arm_ctrl(t):
            arm = control.arm_target_at(path, duration, (t + 1) * dt)
            return jnp.concatenate([arm, env.gripper[:, None].astype(arm.dtype)], -1)

        env = self._phase(env, steps, arm_ctrl, stop_at_success)

        # Gripper phase, only for worlds whose gripper command changes.
        target = control.finger_target(jnp.asarray(actions.gripper, env.gripper.dtype))
        done = self._done(env.outcome, stop_at_success)
        moving = active & ~done & (jnp.abs(target - env.gripper) > 1e-4)
        opening = moving & (target > env.gripper)
        env = self._with_welds(env, env.attached & ~opening[:, None])
        hold = env.physics.ctrl[:, :7]
        start, goal = env.gripper, jnp.where(moving, target, env.gripper)

        def grip_ctrl(t):
            finger = control.gripper_target_at(start, goal, (t + 1) * dt)
            return jnp.concatenate([hold, finger[:, None].astype(hold.dtype)], -1)

        env = self._phase(env, self.gripper_steps * moving, grip_ctrl, stop_at_success)
        done = self._done(env.outcome, stop_at_success)
        closing = moving & ~opening & ~done
        env = env.replace(gripper=jnp.where(moving, target, env.gripper))
        if ep.task.graspables:
            hits = jax.vmap(ep._attach_test)(env.data, env.attached)
            env = self._with_welds(env, env.attached | (hits & closing[:, None]))

        over = (env.outcome == out.RUNNING) & (env.key_actions >= ep.task.max_key_actions)
        return env.replace(outcome=jnp.where(over, out.MAX_STEPS, env.outcome))

    def _done(self, outcome: jax.Array, stop_at_success: bool) -> jax.Array:
        """EnvState.done: evaluation ends at the first success, demonstrations do not."""
        done = outcome != self.outcome.RUNNING
        return done if stop_at_success else done & (outcome != self.outcome.SUCCESS)

    def _phase(self, env: DeviceEnv, steps: jax.Array, ctrl_at, stop_at_success: bool
               ) -> DeviceEnv:
        """Step world w for steps[w] physics steps under ctrl_at(t) (B, nu), checking
        the conditions after each step; update outcomes, step counts and the last row."""
        ep, out = self.ep, self.outcome
        m, d = self.dev.load(env.physics)
        cond_step = jax.vmap(ep._condition_step)
        b = steps.shape[0]
        none = jnp.full(b, -1, jnp.int32)

        def go_on(c):
            return jnp.any(c[-1])

        def one_step(c):
            t, d, data, carry, s_at, f_at, live = c
            new = self.dev.step(m, d, ctrl_at(t))
            new_carry, s, f = cond_step(carry, new.sensordata, env.attached, env.variation)
            carry = jax.tree.map(lambda n, o: keep_rows(live, n, o), new_carry, carry)
            s_at = jnp.where(live & s & (s_at < 0), t, s_at)
            f_at = jnp.where(live & f & (f_at < 0) & (s_at < 0), t, f_at)
            d = freeze(live, new, d)
            data = keep_rows(live, new.sensordata, data)
            ended = (t + 1 >= steps) | (f_at >= 0) | ((s_at >= 0) & stop_at_success)
            return t + 1, d, data, carry, s_at, f_at, live & ~ended

        def body(c):
            # Several masked steps per iteration: a step of a world past its end is undone
            # by `freeze`, so this changes no result, only how often the loop's condition
            # makes the host wait for the device (see steps_per_iteration).
            for _ in range(self.steps_per_iteration):
                c = one_step(c)
            return c

        init = (jnp.int32(0), d, env.data, env.carry, none, none, steps > 0)
        _, d, data, carry, s_at, f_at, _ = jax.lax.while_loop(go_on, body, init)

        active = steps > 0
        succeeded, failed = s_at >= 0, f_at >= 0
        end = jnp.where(succeeded & stop_at_success, s_at, jnp.where(failed, f_at, steps - 1))
        outcome = jnp.where(succeeded, out.SUCCESS,
                            jnp.where(failed, out.FAILURE_CONDITION, env.outcome))
        return env.replace(physics=self.dev.save(env.physics, d), data=data, carry=carry,
                           outcome=outcome,
                           sim_steps=env.sim_steps + jnp.where(active, end + 1, 0).astype(jnp.int32))

    def _with_welds(self, env: DeviceEnv, attached: jax.Array) -> DeviceEnv:
        """Grasp welds on for `attached`; a newly attached object keeps its current pose
        relative to the hand (RLBench's grasp)."""
        scene = self.ep.scene
        if not scene.weld_ids:
            return env
        newly = attached & ~env.attached
        m, d = self.dev.load(env.physics)
        xpos, xquat = self.dev.poses(m, d)
        hp, hq = xpos[:, scene.hand_body], xquat[:, scene.hand_body]
        eq_data, eq_active = env.physics.eq_data, env.physics.eq_active
        for g, (body, eq) in enumerate(zip(scene.graspable_bodies, scene.weld_ids)):
            rel_p = quat_rotate(quat_conj(hq), xpos[:, body] - hp)
            rel_q = quat_mul(quat_conj(hq), xquat[:, body])
            weld = jnp.concatenate([jnp.zeros_like(rel_p), rel_p, rel_q,
                                    jnp.ones_like(rel_p[:, :1])], -1).astype(eq_data.dtype)
            row = eq_data[:, eq, :11]
            eq_data = eq_data.at[:, eq, :11].set(jnp.where(newly[:, g, None], weld, row))
            eq_active = eq_active.at[:, eq].set(attached[:, g])
        physics = env.physics.replace(eq_data=eq_data, eq_active=eq_active)
        return env.replace(physics=physics, attached=attached)


def to_device(env, physics_dtype=jnp.float32) -> DeviceEnv:
    """The device view of a host EnvState (arrays already on the device pass through)."""
    phys = jax.tree.map(
        lambda x: jnp.asarray(x, physics_dtype) if np.dtype(x.dtype) != bool else jnp.asarray(x),
        env.physics)
    return DeviceEnv(
        physics=phys, data=jnp.asarray(env.obs.data, jnp.float32),
        attached=jnp.asarray(env.attached, bool), carry=jax.tree.map(jnp.asarray, env.carry),
        variation=jnp.asarray(env.variation, jnp.int32),
        gripper=jnp.asarray(env.gripper, jnp.float32), outcome=jnp.asarray(env.outcome, jnp.int32),
        key_actions=jnp.asarray(env.key_actions, jnp.int32),
        sim_steps=jnp.asarray(env.sim_steps, jnp.int32))
