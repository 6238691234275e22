"""MJX backends: `impl="warp"` (mujoco-warp, the CUDA fast path) and
`impl="jax"` (any JAX device; used for parity tests on CPU).

The mjx.Model is closed over by the jitted step function, never passed as a
jit argument (passing it made every call slow: docs/performance.md).  The per-world grasp weld data
is the one batched model field.

With several local devices (agnostos_mjx.infra.sharding, ``--devices``) MJX-jax places the
runner's inputs with their world axis split over a mesh, and jit partitions the vmapped
step: worlds are independent, so each device steps its share with no communication.
MJX-warp is not sharded yet: its FFI step needs per-device contact buffers (shard_map),
which wants a multi-GPU test first.
"""

from __future__ import annotations

import functools
import logging
from collections.abc import Callable
from dataclasses import dataclass

import jax
import jax.numpy as jnp
import mujoco
import numpy as np

from agnostos_mjx.infra import sharding
from agnostos_mjx.infra.gc_pause import gc_paused
from agnostos_mjx.physics.base import (
    STATE_FIELDS,
    PhysicsState,
    StepData,
    check_steps,
    for_warp,
    freeze,
    keep_rows,
)
from agnostos_mjx.physics.capabilities import CAPABILITIES
from agnostos_mjx.physics.quiet_mjx import load_mesh_module, mjx

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class DevicePhysics:
    """Pure, jittable pieces of an MJX backend for one batch size.

    load(state) -> (model, data): the per-world model (grasp weld data, MJX-jax's mocap
        fix) and data of a `PhysicsState`;
    step(model, data, ctrl (B, nu)) -> data: one physics step of every world;
    poses(model, data) -> (xpos (B, nbody, 3), xquat (B, nbody, 4)) at the current qpos;
    save(state, data) -> state: the `PhysicsState` of `data`;
    steps(model, data, ctrl (K, B, nu)) -> (data, rows): K steps at once where a backend has
        a faster way than K `step`s (physics/warp_chunk.py); see `run_steps`."""

    load: Callable[[PhysicsState], tuple[mjx.Model, mjx.Data]]
    step: Callable[[mjx.Model, mjx.Data, jax.Array], mjx.Data]
    poses: Callable[[mjx.Model, mjx.Data], tuple[jax.Array, jax.Array]]
    save: Callable[[PhysicsState, mjx.Data], PhysicsState]
    steps: Callable[[mjx.Model, mjx.Data, jax.Array], tuple[mjx.Data, mjx.Data]] | None = None

    def run_steps(self, m: mjx.Model, d: mjx.Data, ctrl: jax.Array) -> tuple[mjx.Data, mjx.Data]:
        """K steps of every world with per-step controls ctrl (K, B, nu): the data after the
        last step, and `rows`, a data whose STATE_FIELDS and sensordata hold each step's
        values along a leading K axis (every world steps K times; the caller freezes)."""
        if self.steps is not None:
            return self.steps(m, d, ctrl)

        def body(d: mjx.Data, u: jax.Array) -> tuple[mjx.Data, tuple]:
            new = self.step(m, d, u)
            return new, tuple(getattr(new, f) for f in (*STATE_FIELDS, "sensordata"))

        last, rows = jax.lax.scan(body, d, ctrl)
        return last, last.replace(**dict(zip((*STATE_FIELDS, "sensordata"), rows, strict=True)))


# Contact and constraint rows MuJoCo Warp allocates per world (naconmax = batch x contacts).
CONTACTS_PER_WORLD = 64
CONSTRAINTS_PER_WORLD = 256


class MjxBackend:
    def __init__(self, model: mujoco.MjModel, impl: str = "jax",
                 contacts_per_world: int = CONTACTS_PER_WORLD,
                 constraints_per_world: int = CONSTRAINTS_PER_WORLD,
                 graph_mode: str = "WARP"):
        self.name = f"mjx-{impl}"
        self.impl = impl
        self.capabilities = CAPABILITIES[impl]
        self.model = for_warp(model) if impl == "warp" else model
        model = self.model
        options = {}
        if impl == "warp":
            # The graph mode of MJX's own FFI calls (`mjx.step`, `mjx.kinematics`), which
            # only scenes the direct K-step call does not support use (warp_steps_direct).
            from mujoco.mjx.warp import types as warp_types

            options["graph_mode"] = getattr(warp_types.GraphMode, graph_mode)
        else:
            load_mesh_module()  # MJX-jax's put_model converts the scene's meshes
        self.mx = mjx.put_model(model, impl=impl, **options)
        self.contacts_per_world = contacts_per_world
        self.constraints_per_world = constraints_per_world
        mesh = sharding.mesh() if self.capabilities.sharded else None
        self.mesh = mesh if mesh is not None and sharding.device_count(mesh) > 1 else None

    @functools.lru_cache(maxsize=16)
    def device_physics(self, batch: int) -> DevicePhysics:
        """The pure pieces of this backend for a batch of `batch` worlds, for jitted
        programs that fuse physics with control and conditions (runtime.phase.DevicePhases)."""
        mx = self.mx
        impl = self.impl
        if impl == "warp" and warp_steps_direct(self.model):
            return direct_warp_physics(self.model, batch, naconmax=batch * self.contacts_per_world,
                                       njmax=self.constraints_per_world)
        # make_data wants the MjModel for warp and accepts the mjx.Model for jax.
        source = self.model if impl == "warp" else mx
        kwargs = {}
        if impl == "warp":
            kwargs = dict(naconmax=batch * self.contacts_per_world, njmax=self.constraints_per_world)
        # Batch the model's weld data only when the task has grasp welds beyond
        # the finger coupling; an unbatched model keeps the fast path.
        batched_eq = self.model.neq > 1
        model_axes = jax.tree.map(lambda _: None, mx)
        if batched_eq:
            model_axes = model_axes.tree_replace({"eq_data": 0})
        # MJX-jax places the children of mocap bodies from the compiled body
        # poses, so the per-world mocap pose goes into body_pos/body_quat too
        # (mocap bodies are children of the world, so this is exact).
        mocap_bodies = np.nonzero(self.model.body_mocapid >= 0)[0]
        mocap_rows = self.model.body_mocapid[mocap_bodies]
        fix_mocap = impl == "jax" and len(mocap_bodies) > 0
        if fix_mocap:
            model_axes = model_axes.tree_replace({"body_pos": 0, "body_quat": 0})
        model_batched = batched_eq or fix_mocap

        def load(state: PhysicsState) -> tuple[mjx.Model, mjx.Data]:
            m = mx.tree_replace({"eq_data": state.eq_data}) if batched_eq else mx
            if fix_mocap:
                b = state.qpos.shape[0]
                pos = jnp.broadcast_to(mx.body_pos, (b, *mx.body_pos.shape))
                quat = jnp.broadcast_to(mx.body_quat, (b, *mx.body_quat.shape))
                pos = pos.at[:, mocap_bodies].set(state.mocap_pos[:, mocap_rows])
                quat = quat.at[:, mocap_bodies].set(state.mocap_quat[:, mocap_rows])
                m = m.tree_replace({"body_pos": pos, "body_quat": quat})
            # Zero-filled Data made inside the program (a device memset), so no template
            # batch is baked into it as a constant.
            d = jax.vmap(lambda _: mjx.make_data(source, impl=impl, **kwargs))(jnp.arange(batch))
            d = d.replace(qpos=state.qpos, qvel=state.qvel, act=state.act, ctrl=state.ctrl,
                          mocap_pos=state.mocap_pos, mocap_quat=state.mocap_quat,
                          eq_active=state.eq_active, time=state.time)
            return m, d

        def per_world(fn: Callable) -> Callable:
            """fn(model, data, *args) of one world -> the batched function."""
            if model_batched:
                return lambda m, d, *args: jax.vmap(fn, in_axes=(model_axes, 0) + (0,) * len(args))(
                    m, d, *args)
            # close over the model, as MJX advises, when no field is per world
            return lambda m, d, *args: jax.vmap(lambda d, *a: fn(mx, d, *a))(d, *args)

        step = per_world(lambda m, d, u: mjx.step(m, d.replace(ctrl=u)))

        def pose(m: mjx.Model, d: mjx.Data) -> tuple[jax.Array, jax.Array]:
            k = mjx.kinematics(m, d)
            return k.xpos, k.xquat

        poses = per_world(pose)

        def save(state: PhysicsState, d: mjx.Data) -> PhysicsState:
            return state.replace(qpos=d.qpos, qvel=d.qvel, act=d.act, ctrl=d.ctrl,
                                 mocap_pos=d.mocap_pos, mocap_quat=d.mocap_quat,
                                 eq_active=d.eq_active, time=d.time)

        return DevicePhysics(load=load, step=step, poses=poses, save=save)

    @functools.lru_cache(maxsize=16)
    def _runner(self, batch: int, nstep: int):
        dev = self.device_physics(batch)

        @jax.jit
        def run(state: PhysicsState, ctrl: jnp.ndarray, steps: jnp.ndarray):
            m, d = dev.load(state)

            def body(carry, inputs):
                # One scan over the longest move; a world past its own end keeps its state
                # (and its last sensor row), so per-world lengths never change a shape.
                d, sens = carry
                u, t = inputs
                new = dev.step(m, d, u)
                live = t < steps
                d = freeze(live, new, d)
                sens = keep_rows(live, new.sensordata, sens)
                return (d, sens), sens

            (d, _), sens = jax.lax.scan(body, (d, d.sensordata),
                                        (jnp.swapaxes(ctrl, 0, 1), jnp.arange(ctrl.shape[1])))
            return dev.save(state, d), jnp.swapaxes(sens, 0, 1)

        return run

    def run(self, state: PhysicsState, ctrl: np.ndarray, steps: np.ndarray | None = None
            ) -> tuple[PhysicsState, np.ndarray]:
        """See Backend.run: one device call whatever the per-world step counts."""
        steps = jnp.asarray(check_steps(steps, state.batch, int(np.shape(ctrl)[1])))
        state = jax.tree.map(lambda x: jnp.asarray(x, jnp.float32) if x.dtype != bool else jnp.asarray(x), state)
        ctrl = jnp.asarray(ctrl, jnp.float32)
        n = state.batch
        if self.mesh is not None:  # padded worlds repeat the last one; cut from the results
            (state, ctrl, steps), n = sharding.shard((state, ctrl, steps), self.mesh)
        runner = self._runner(state.batch, int(ctrl.shape[1]))
        if not self.capabilities.captures_graphs:
            return sharding.unpad(runner(state, ctrl, steps), n)
        with gc_paused():
            return jax.block_until_ready(runner(state, ctrl, steps))


def warp_steps_direct(model: mujoco.MjModel) -> bool:
    """Whether the warp backend steps MuJoCo Warp directly, K steps per FFI call
    (physics/warp_chunk.py): for every scene that call supports.  It is faster per key
    action than MJX's one-call-per-step `mjx.step` (docs/performance.md), and gives native
    MuJoCo's outcomes where `mjx.step` in graph mode WARP gave wrong ones once several tasks
    ran in one process.  Other scenes step through `mjx.step`, with a warning."""
    from agnostos_mjx.physics import warp_chunk

    why_not = warp_chunk.supported(model)
    if why_not:
        _warn_mjx_steps(why_not)
    return why_not is None


@functools.cache
def _warn_mjx_steps(reason: str) -> None:
    log.warning("warp: this scene steps through MJX's mjx.step (the direct call does not "
                "carry %s); in graph mode WARP mjx.step gave wrong outcomes once several "
                "tasks ran in one process", reason)


def direct_warp_physics(model: mujoco.MjModel, batch: int, naconmax: int, njmax: int
                        ) -> DevicePhysics:
    """DevicePhysics of MuJoCo Warp called directly (physics/warp_chunk.py): K steps per FFI
    call, and the poses from its kinematics, so no MJX FFI call is left in a key action."""
    from agnostos_mjx.physics.warp_chunk import warp_chunk

    chunk = warp_chunk(model, batch, naconmax, njmax)
    return DevicePhysics(load=lambda state: (None, StepData.start(state, model.nsensordata)),
                         step=lambda _, d, u: chunk(d, u[None])[0],
                         poses=lambda _, d: chunk.poses(d), save=lambda state, d: d.saved(state),
                         steps=lambda _, d, ctrl: chunk(d, ctrl))
