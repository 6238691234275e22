"""The two kinds of physics boundary under the key action (runtime/key_action.py).

`HostPhases`: any backend's `run(state, ctrl, steps)` (native MuJoCo's rollout threads, or
MJX for recorded demonstrations): the phase's controls are computed for all its steps at
once, the physics runs, then the conditions are scanned over the recorded sensor rows.

`DevicePhases`: inside one jitted program next to MJX: a `lax.while_loop` over physics
steps (K per iteration, in one physics call), controls read at each step from the plan,
conditions checked after every step, a world frozen at its own end (last step, failure, or
success when episodes stop there), and the loop stops when no world is left moving.  A world
that finished mid-phase keeps its state at that step here, where the host path steps it to
the phase's end; the episode is over either way and its final observation is the same.

Both report the first success and failure step of each world in the same way (a failure
counts only before any success), so the key action above them is one piece of code.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import TYPE_CHECKING, Any

import jax
import jax.numpy as jnp
import mujoco
import numpy as np

from agnostos_mjx.physics import CAPABILITIES
from agnostos_mjx.physics.base import STATE_FIELDS, Backend, PhysicsState, freeze, keep_rows
from agnostos_mjx.runtime.outcome import phase_end
from agnostos_mjx.runtime.state import EnvState, StepResult
from agnostos_mjx.sim.world import posed_data

if TYPE_CHECKING:  # native physics never imports MJX (and its scipy, trimesh)
    from agnostos_mjx.physics.mjx_backend import DevicePhysics


def scan_conditions(condition_step: Callable) -> Callable:
    """One world's condition trees scanned over a phase's rows: (carry, data (T, S),
    attached (T, G), valid (T,), variation) -> (carry, first success step or -1, first
    failure step or -1); rows past the world's end (valid False) change nothing."""

    def run(carry, data, attached, valid, variation):
        def body(c, inputs):
            d, a, v = inputs
            new, s, f = condition_step(c, d, a, variation)
            keep = lambda n, o: jnp.where(v, n, o)  # noqa: E731
            return jax.tree.map(keep, new, c), (s & v, f & v)

        carry, (s, f) = jax.lax.scan(body, carry, (data, attached, valid))
        first = lambda m: jnp.where(jnp.any(m), jnp.argmax(m), -1)  # noqa: E731
        return carry, first(s), first(f)

    return run


# Rows per call of the host's condition program: one compiled shape for every phase length.
CONDITION_ROWS = 128


def condition_rows(steps: int) -> int:
    """Rows per condition call for phases of at most `steps` steps (a dense control period):
    the next power of two, at least 8, at most CONDITION_ROWS, so that short phases do not
    scan a whole chunk of padding rows."""
    return min(CONDITION_ROWS, max(8, 1 << (max(steps, 1) - 1).bit_length()))


def host_device() -> jax.Device | None:
    """The CPU, where a host key action runs its small jitted helpers (the condition scan,
    grasps) next to its physics: on a GPU host each call would otherwise wait behind the
    other programs queued there (py-spy of 8 processes on one GPU: the physics threads
    waited on condition scans longer than on their rollouts).  None where the CPU is JAX's default
    already (a device set explicitly would key new entries in jit's caches) or JAX may not
    use it (JAX_PLATFORMS without cpu)."""
    if jax.default_backend() == "cpu":
        return None
    try:
        return jax.local_devices(backend="cpu")[0]
    except RuntimeError:  # "Unknown backend cpu"
        return None


class HostPhases:
    """Phases through a backend's `run`, on the host (numpy)."""

    xp = np

    def __init__(self, backend: Backend, model: mujoco.MjModel, conditions: Callable,
                 record_qpos: bool = False, rows: int = CONDITION_ROWS):
        """`conditions`: `jax.jit(jax.vmap(scan_conditions(condition_step)))`, made once per
        runner (a new jit per key action would compile anew each time); `rows`: rows per
        call of it (`condition_rows`)."""
        self.backend = backend
        self.model = model
        self.record_qpos = record_qpos
        self._conditions = conditions
        self.rows = rows

    def run_phase(self, state: EnvState, steps: np.ndarray, ctrl_at: Callable
                  ) -> tuple[EnvState, np.ndarray, np.ndarray, StepResult | None]:
        active = steps > 0
        none = np.full(len(steps), -1)
        if not active.any():
            return state, none, none, None
        t = int(steps.max())
        ctrl = ctrl_at(np.arange(t))
        if self.record_qpos:
            physics, sens, qpos = self.backend.run_with_qpos(state.physics, ctrl, steps)
        else:
            (physics, sens), qpos = self.backend.run(state.physics, ctrl, steps), None
        sens = np.array(sens, copy=True)
        sens[~active] = np.asarray(state.data)[~active][:, None]
        attached = np.repeat(state.attached[:, None], t, axis=1)
        valid = np.arange(t)[None] < steps[:, None]
        carry, s_idx, f_idx = self._scan(state, sens, attached, valid)
        # A failure ends the episode unless success came first (or at the same step); a
        # success after a failure does not count.
        failed = active & (f_idx >= 0) & ~((s_idx >= 0) & (s_idx <= f_idx))
        success_at = np.where(active & (s_idx >= 0) & ~failed, s_idx, -1)
        failure_at = np.where(failed, f_idx, -1)
        end = phase_end(steps, success_at, failure_at, state.stop_at_success, np)
        last = sens[np.arange(len(end)), np.maximum(end, 0)]
        data = np.where(active[:, None], last, np.asarray(state.data))
        record = StepResult(sens, attached, valid & (np.arange(t)[None] <= end[:, None]), qpos)
        # Native MuJoCo runs each world its own steps (physics/native.py).
        new = state.replace(physics=physics.numpy(), data=data, carry=carry,
                            world_steps=state.world_steps + steps)
        return new, success_at, failure_at, record

    def _scan(self, state: EnvState, sens: np.ndarray, attached: np.ndarray, valid: np.ndarray
              ) -> tuple[Any, np.ndarray, np.ndarray]:
        """The conditions over a phase's rows in chunks of `self.rows` (the last one
        padded with rows that are not valid), so a runner compiles one condition program
        whatever its phases' lengths; returns the carry and the first success and failure
        rows (-1: none)."""
        b, t = valid.shape
        carry, none = state.carry, np.full(b, -1)
        s_idx, f_idx = none, none
        for start in range(0, t, self.rows):
            rows = [x[:, start:start + self.rows] for x in (sens, attached, valid)]
            pad = self.rows - rows[0].shape[1]
            if pad:  # the last row repeated, marked not valid
                rows = [np.concatenate([x, np.repeat(x[:, -1:], pad, axis=1)], axis=1)
                        for x in rows]
                rows[2][:, -pad:] = False
            carry, s, f = self._conditions(carry, *rows, state.variation)
            s, f = np.asarray(s), np.asarray(f)
            s_idx = np.where((s_idx < 0) & (s >= 0), s + start, s_idx)
            f_idx = np.where((f_idx < 0) & (f >= 0), f + start, f_idx)
        return jax.tree.map(np.asarray, carry), s_idx, f_idx

    def poses(self, physics: PhysicsState, worlds: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        b, nbody = len(worlds), self.model.nbody
        xpos, xquat = np.zeros((b, nbody, 3)), np.zeros((b, nbody, 4))
        for w in np.nonzero(worlds)[0]:
            data = posed_data(self.model, physics, w)
            xpos[w], xquat[w] = data.xpos, data.xquat
        return xpos, xquat


def steps_per_iteration(backend_name: str) -> int:
    """Physics steps per iteration of a device phase's while loop, as the backend declares
    (Capabilities.steps_per_iteration): 16 on warp, else 1.

    Each iteration ends with the host reading the loop's condition from the device.  With
    K > 1 an iteration is one physics call of K steps (`DevicePhysics.run_steps`: on warp
    one FFI call, physics/warp_chunk.py), after which the conditions run over the K rows and
    a world that ended inside is set back to its end step: bit for bit the one-step loop's
    result (tests/test_k_steps.py), at one Python FFI callback per K steps instead of one
    per step.  K = 16, 32 and 64 cost the same at 75 worlds, in one process and in the
    8-process main job (docs/performance.md); a finished world idles at most K - 1
    steps.  On MJX-jax (CPU tests) one step per iteration keeps the program small."""
    return CAPABILITIES[backend_name].steps_per_iteration


class DevicePhases:
    """Phases as `lax.while_loop`s of MJX steps, traced into the key action's program."""

    xp = jnp

    def __init__(self, dev: DevicePhysics, condition_step: Callable, steps_per_iteration: int):
        self.dev = dev
        self.steps_per_iteration = steps_per_iteration
        self._check = jax.vmap(condition_step)

    def run_phase(self, state: EnvState, steps: jax.Array, ctrl_at: Callable
                  ) -> tuple[EnvState, jax.Array, jax.Array, None]:
        stop = state.stop_at_success
        m, d = self.dev.load(state.physics)
        b = steps.shape[0]
        none = jnp.full(b, -1, jnp.int32)

        def check(c: tuple, sensors: jax.Array) -> tuple:
            """The conditions after one step of the live worlds (whose sensor rows these are)."""
            t, data, carry, s_at, f_at, live = c
            new_carry, s, f = self._check(carry, sensors, state.attached, state.variation)
            carry = jax.tree.map(lambda n, o: keep_rows(live, n, o), new_carry, carry)
            s_at = jnp.where(live & s & (s_at < 0), t, s_at)
            f_at = jnp.where(live & f & (f_at < 0) & (s_at < 0), t, f_at)
            data = keep_rows(live, sensors, data)
            ended = (t + 1 >= steps) | (f_at >= 0) | ((s_at >= 0) & stop)
            return t + 1, data, carry, s_at, f_at, live & ~ended

        def one_step(c: tuple) -> tuple:
            t, d, data, carry, s_at, f_at, live = c
            new = self.dev.step(m, d, ctrl_at(t[None])[:, 0])
            t, data, carry, s_at, f_at, after = check((t, data, carry, s_at, f_at, live),
                                                      new.sensordata)
            return t, freeze(live, new, d), data, carry, s_at, f_at, after

        def k_steps(c: tuple) -> tuple:
            # K steps of every world in one physics call (on warp: one FFI call), then the
            # conditions over the K sensor rows as the one-step loop checks them; a world
            # that ended at row i is set back to its state after step i (every world
            # stepped on to the K-th; a world ended before the chunk keeps its state).
            # Bit for bit the one-step loop's result (tests/test_k_steps.py, test_key_action.py).
            t, d, data, carry, s_at, f_at, live = c
            k = self.steps_per_iteration
            ctrl = jnp.swapaxes(ctrl_at(t + jnp.arange(k)), 0, 1)
            last, rows = self.dev.run_steps(m, d, ctrl)

            def row(c: tuple, inputs: tuple) -> tuple:
                (*checked, end), (sensors, i) = c, inputs
                end = jnp.where(checked[-1], i, end)
                return (*check(tuple(checked), sensors), end), None

            # A counted loop over the rows: unrolling it measured the same (docs/performance.md).
            (t, data, carry, s_at, f_at, after, end), _ = jax.lax.scan(
                row, (t, data, carry, s_at, f_at, live, none), (rows.sensordata, jnp.arange(k)))
            at_end = lambda r, old: keep_rows(end >= 0, r[jnp.maximum(end, 0), jnp.arange(b)], old)  # noqa: E731
            d = last.replace(**{f: at_end(getattr(rows, f), getattr(d, f)) for f in STATE_FIELDS})
            return t, d, data, carry, s_at, f_at, after

        body = one_step if self.steps_per_iteration == 1 else k_steps
        init = (jnp.int32(0), d, state.data, state.carry, none, none, steps > 0)
        t, d, data, carry, s_at, f_at, _ = jax.lax.while_loop(lambda c: jnp.any(c[-1]), body, init)
        # Every world is stepped (frozen ones too) until the last live world ends.
        new = state.replace(physics=self.dev.save(state.physics, d), data=data, carry=carry,
                            world_steps=state.world_steps + t)
        return new, s_at, f_at, None

    def poses(self, physics: PhysicsState, worlds: Any) -> tuple[jax.Array, jax.Array]:
        return self.dev.poses(*self.dev.load(physics))
