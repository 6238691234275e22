"""MJX backends: `impl="warp"` (mujoco-warp, the CUDA fast path) and
`impl="jax"` (any JAX device; used for parity tests on CPU).

The mjx.Model is closed over by the jitted step function, never passed as a
jit argument (passing it cost ~0.9 s a call).  The per-world grasp weld data
is the one batched model field.

With several local devices (agnostos_mjx.sharding, ``--devices``) MJX-jax places the
runner's inputs with their world axis split over a mesh, and jit partitions the vmapped
step: worlds are independent, so each device steps its share with no communication.
MJX-warp is not sharded yet: its FFI step needs per-device contact buffers (shard_map),
which wants a multi-GPU test first.
"""

from __future__ import annotations

import contextlib
import functools
import gc
from collections.abc import Iterator

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
from mujoco import mjx

from agnostos_mjx import sharding
from agnostos_mjx.physics.base import PhysicsState, check_steps


class MjxBackend:
    def __init__(self, model: mujoco.MjModel, impl: str = "jax",
                 contacts_per_world: int = 64, constraints_per_world: int = 256,
                 graph_mode: str = "WARP_STAGED"):
        self.name = f"mjx-{impl}"
        self.impl = impl
        self.model = model
        options = {}
        if impl == "warp":
            # Warp's default graph mode replays a CUDA graph only for matching
            # buffer addresses; per-step controls change them every step, which
            # forced a recapture per step (83k env-steps/s at batch 1024 on an
            # H200) and, measured with tools/warp_variants.py, returned stale
            # sensor data at batch 1024.  The staged mode copies into fixed
            # buffers: 500k env-steps/s at batch 1024 with correct data.
            from mujoco.mjx.warp import types as warp_types

            options["graph_mode"] = getattr(warp_types.GraphMode, graph_mode)
        self.mx = mjx.put_model(model, impl=impl, **options)
        self.contacts_per_world = contacts_per_world
        self.constraints_per_world = constraints_per_world
        mesh = sharding.mesh() if impl == "jax" else None
        self.mesh = mesh if mesh is not None and sharding.device_count(mesh) > 1 else None

    @functools.lru_cache(maxsize=16)
    def _runner(self, batch: int, nstep: int):
        mx = self.mx
        impl = self.impl
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

        # A template batch of Data, made once per batch size and passed in,
        # so each rollout only overwrites the state fields.
        template = jax.jit(jax.vmap(lambda _: mjx.make_data(source, impl=impl, **kwargs)))(
            jnp.arange(batch))
        if self.mesh is not None:
            template = jax.device_put(template, sharding.batch_sharding(self.mesh))

        def to_data(template, state: PhysicsState):
            return template.replace(qpos=state.qpos, qvel=state.qvel, act=state.act,
                                    ctrl=state.ctrl, mocap_pos=state.mocap_pos,
                                    mocap_quat=state.mocap_quat, eq_active=state.eq_active,
                                    time=state.time)

        def step(m, d, u):
            return mjx.step(m, d.replace(ctrl=u))

        model_batched = batched_eq or fix_mocap
        if model_batched:
            batched_step = jax.vmap(step, in_axes=(model_axes, 0, 0))
        else:  # close over the model, as MJX advises, when no field is per world
            batched_step = lambda m, d, u: jax.vmap(lambda d, u: step(mx, d, u))(d, u)  # noqa: E731

        @jax.jit
        def run(template, state: PhysicsState, ctrl: jnp.ndarray, steps: jnp.ndarray):
            m = mx.tree_replace({"eq_data": state.eq_data}) if batched_eq else mx
            if fix_mocap:
                b = state.qpos.shape[0]
                pos = jnp.broadcast_to(mx.body_pos, (b, *mx.body_pos.shape))
                quat = jnp.broadcast_to(mx.body_quat, (b, *mx.body_quat.shape))
                pos = pos.at[:, mocap_bodies].set(state.mocap_pos[:, mocap_rows])
                quat = quat.at[:, mocap_bodies].set(state.mocap_quat[:, mocap_rows])
                m = m.tree_replace({"body_pos": pos, "body_quat": quat})
            d = to_data(template, state)

            def body(carry, inputs):
                # One scan over the longest move; a world past its own end keeps its state
                # (and its last sensor row), so per-world lengths never change a shape.
                d, sens = carry
                u, t = inputs
                new = batched_step(m, d, u)
                live = t < steps
                keep = lambda a, b: jnp.where(live.reshape(-1, *[1] * (a.ndim - 1)), a, b)  # noqa: E731
                d = new.replace(qpos=keep(new.qpos, d.qpos), qvel=keep(new.qvel, d.qvel),
                                act=keep(new.act, d.act), time=keep(new.time, d.time))
                sens = keep(new.sensordata, sens)
                return (d, sens), sens

            (d, _), sens = jax.lax.scan(body, (d, d.sensordata),
                                        (jnp.swapaxes(ctrl, 0, 1), jnp.arange(ctrl.shape[1])))
            last = jnp.take_along_axis(ctrl, jnp.maximum(steps - 1, 0)[:, None, None], 1)[:, 0]
            new = state.replace(qpos=d.qpos, qvel=d.qvel, act=d.act,
                                ctrl=jnp.where((steps > 0)[:, None], last, state.ctrl),
                                mocap_pos=d.mocap_pos, mocap_quat=d.mocap_quat,
                                eq_active=d.eq_active, time=d.time)
            return new, jnp.swapaxes(sens, 0, 1)

        return functools.partial(run, template)

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
        if self.impl != "warp":
            return sharding.unpad(runner(state, ctrl, steps), n)
        with gc_paused():
            return jax.block_until_ready(runner(state, ctrl, steps))


@contextlib.contextmanager
def gc_paused() -> Iterator[None]:
    """Keep Python's cyclic garbage collector off while Warp captures CUDA graphs.

    Warp runs the MJX step as Python code inside an XLA FFI callback and captures it
    into a CUDA graph.  A collection there may free an old XLA executable (e.g. the
    previous task's runner); XLA then unloads its CUDA module, which is illegal while a
    stream captures, and the capture fails ("Warp CUDA error 901 ... during capture",
    seen on an H200 in the 19th task of a default run).  The caller waits for the
    result inside this block, so the callback has finished before collection resumes.
    """
    was_enabled = gc.isenabled()
    gc.disable()
    try:
        yield
    finally:
        if was_enabled:
            gc.enable()
