"""graph_jit: the GPU's programs with loops compile as CUDA graphs, other backends as before."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from agnostos_mjx.infra import cuda_graphs
from agnostos_mjx.infra.cuda_graphs import GPU_GRAPH_OPTIONS, graph_jit
from agnostos_mjx.sim import control


def _doubling(x: jax.Array, n: int) -> jax.Array:
    return jax.lax.fori_loop(0, n, lambda i, a: a * 2.0, x)


def test_graph_jit_asks_for_cuda_graphs_only_where_the_backend_is_a_gpu(monkeypatch):
    want = np.asarray(jax.jit(_doubling, static_argnums=1)(jnp.ones(3), 4))
    options = []
    real_jit = jax.jit

    def spy(fn, **kwargs):
        options.append(kwargs.get("compiler_options"))
        return real_jit(fn, **kwargs)

    monkeypatch.setattr(cuda_graphs.jax, "jit", spy)
    fn = graph_jit(_doubling, static_argnums=1)
    np.testing.assert_array_equal(fn(jnp.ones(3), 4), want)
    np.testing.assert_array_equal(fn(jnp.ones(3), 4), want)  # compiled once per backend
    assert options == [None] and set(fn.programs) == {"cpu"}

    monkeypatch.setattr(cuda_graphs.jax, "default_backend", lambda: "gpu")
    np.testing.assert_array_equal(fn(jnp.ones(3), 4), want)  # the CPU ignores GPU options
    assert options == [None, GPU_GRAPH_OPTIONS] and set(fn.programs) == {"cpu", "gpu"}


def test_lower_compiles_the_program_a_call_runs():
    """`lower` (the warm-up's ahead-of-time compile) lowers the very program a call runs:
    one jitted function per backend, the same text."""
    fn = graph_jit(_doubling, static_argnums=1)
    lowered = fn.lower(jnp.ones(3), 4)
    assert set(fn.programs) == {"cpu"}
    np.testing.assert_array_equal(lowered.compile()(jnp.ones(3)), fn(jnp.ones(3), 4))
    assert set(fn.programs) == {"cpu"}
    assert lowered.as_text() == fn.programs["cpu"].lower(jnp.ones(3), 4).as_text()


def test_the_planner_runs_its_loops_as_cuda_graphs():
    """Without graphs a GPU host's thread waiting for a plan spins on every iteration's
    predicate."""
    from agnostos_mjx.runtime.env import Episodes
    from agnostos_mjx.tasks import get_task

    kin = Episodes(get_task("lamp_on"), "native").kin
    for fn in (control.plan_arm, control.reachable):
        assert hasattr(control.jit_for_robot(fn, kin), "programs")
