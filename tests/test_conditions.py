"""Success conditions with RLBench semantics (spec section 3), on hand-built
observations, then each task's success condition on real episodes."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from agnostos_mjx.runtime.outcome import Outcome
from agnostos_mjx.sim.conditions import (
    AllOf,
    AnyOf,
    Detected,
    Grasped,
    JointMoved,
    NothingGrasped,
    all_of,
)
from agnostos_mjx.sim.math3d import yaw_quat
from agnostos_mjx.sim.observables import Layout, Observation
from agnostos_mjx.tasks import get_task, list_tasks
from tests.conftest import episodes_for, task_params

LAYOUT = Layout((
    ("a.q", 0, 1),
    ("b.q", 1, 1),
    ("c.q", 2, 1),
    ("obj.pos", 3, 3),
    ("obj.quat", 6, 4),
    ("vol.pos", 10, 3),
    ("vol.quat", 13, 4),
))
VOL_POS = np.array([0.5, 0.2, 0.8])
VOL_QUAT = np.asarray(yaw_quat(np.pi / 2))  # volume x axis along world +y
VOL_HALF = (0.10, 0.02, 0.05)


def make_obs(q=(0.0, 0.0, 0.0), obj=VOL_POS, attached=(False, False)) -> Observation:
    data = np.concatenate([q, obj, [1.0, 0.0, 0.0, 0.0], VOL_POS, VOL_QUAT]).astype(np.float32)
    assert data.shape == (LAYOUT.size,)
    return Observation(jnp.asarray(data), LAYOUT, jnp.asarray(attached))


def run(cond, observations) -> list[bool]:
    """init on the first observation, then step through all of them."""
    carry = cond.init(observations[0])
    out = []
    for obs in observations:
        carry, met = cond.step(carry, obs)
        out.append(bool(met))
    return out


def joints(*qs) -> list[Observation]:
    return [make_obs(q=q) for q in qs]


# ---- JointMoved ------------------------------------------------------------------------
def test_joint_moved_threshold_both_sides_and_direction_ignored():
    cond = JointMoved(("a",), 0.05)
    start = make_obs(q=(0.1, 0.0, 0.0))
    carry = cond.init(start)
    cases = {0.1: False, 0.149: False, 0.151: True, 0.051: False, 0.049: True, 0.5: True}
    for q, expected in cases.items():
        _, met = cond.step(carry, make_obs(q=(q, 0.0, 0.0)))
        assert bool(met) is expected, q
    # Other joints moving does not count.
    _, met = cond.step(carry, make_obs(q=(0.1, 1.0, -1.0)))
    assert not bool(met)


def test_joint_moved_measures_from_reset_value():
    """The reference is the joint value at init, not zero."""
    cond = JointMoved(("a",), 0.05)
    assert run(cond, joints((0.7, 0, 0), (0.7, 0, 0), (0.72, 0, 0))) == [False] * 3
    assert run(cond, joints((0.7, 0, 0), (0.6, 0, 0))) == [False, True]


def test_joint_moved_traced_index_under_jit_and_vmap():
    names = ("a", "b", "c")

    @jax.jit
    def met(index, data0, data1):
        cond = JointMoved(names, 0.05, index=index)
        o0 = Observation(data0, LAYOUT, jnp.zeros(2, bool))
        o1 = Observation(data1, LAYOUT, jnp.zeros(2, bool))
        return cond.step(cond.init(o0), o1)[1]

    d0 = make_obs().data
    moved_b = make_obs(q=(0.0, -0.2, 0.0)).data
    assert [bool(met(jnp.int32(i), d0, moved_b)) for i in range(3)] == [False, True, False]

    # One world per joint, each moving only its own joint: all met; shifted: none.
    d1 = jnp.stack([make_obs(q=np.eye(3)[i] * 0.2).data for i in range(3)])
    d0s = jnp.stack([d0] * 3)
    batched = jax.vmap(met)
    assert np.asarray(batched(jnp.arange(3), d0s, d1)).tolist() == [True, True, True]
    assert np.asarray(batched(jnp.array([1, 2, 0]), d0s, d1)).tolist() == [False] * 3


# ---- Detected ----------------------------------------------------------------------------
def detected(offset, radius=0.0, negated=False) -> bool:
    cond = Detected("obj", "vol", VOL_HALF, radius=radius, negated=negated)
    obs = make_obs(obj=VOL_POS + np.asarray(offset))
    return bool(cond.step(cond.init(obs), obs)[1])


def test_detected_inside_and_outside_rotated_box():
    assert detected((0.0, 0.0, 0.0))
    # The volume is yawed 90 degrees: its long x half-extent (0.10) lies along world y.
    assert detected((0.0, 0.08, 0.0))
    assert detected((0.0, -0.09, 0.04))
    assert not detected((0.08, 0.0, 0.0))  # along world x only 0.02 of room
    assert not detected((0.0, 0.11, 0.0))
    assert not detected((0.0, 0.0, 0.06))


def test_detected_radius_grows_volume():
    offset = (0.05, 0.0, 0.0)  # 0.03 outside the volume's local y face
    assert not detected(offset, radius=0.02)
    assert detected(offset, radius=0.035)


def test_detected_negated():
    assert not detected((0.0, 0.0, 0.0), negated=True)
    assert detected((0.3, 0.0, 0.0), negated=True)


# ---- grasp conditions ----------------------------------------------------------------------
@pytest.mark.parametrize("attached, nothing, first, second", [
    ((False, False), True, False, False),
    ((True, False), False, True, False),
    ((False, True), False, False, True),
])
def test_grasp_conditions_read_attached(attached, nothing, first, second):
    obs = make_obs(attached=attached)
    for cond, expected in ((NothingGrasped(), nothing), (Grasped(0), first), (Grasped(1), second)):
        assert bool(cond.step(cond.init(obs), obs)[1]) is expected


# ---- AllOf / AnyOf -------------------------------------------------------------------------
A, B, C = (JointMoved((j,), 0.5) for j in "abc")


def test_all_of_unordered_needs_all_at_once():
    cond = AllOf((A, B))
    assert run(cond, joints((0, 0, 0), (1, 0, 0), (1, 1, 0))) == [False, False, True]
    # Each held once, never together: not met (no memory without ordering).
    assert run(cond, joints((0, 0, 0), (1, 0, 0), (0, 1, 0))) == [False, False, False]
    # Order is irrelevant.
    assert run(cond, joints((0, 0, 0), (0, 1, 0), (1, 1, 0))) == [False, False, True]


def test_all_of_ordered_progress_persists():
    cond = all_of([A, B], ordered=True)
    # A, released, then B: progress from A persists.
    assert run(cond, joints((0, 0, 0), (1, 0, 0), (0, 0, 0), (0, 1, 0))) == [
        False, False, False, True]


def test_all_of_ordered_wrong_order_waits_for_earlier():
    cond = all_of([A, B], ordered=True)
    seq = joints((0, 0, 0), (0, 1, 0), (0, 0, 0), (1, 0, 0), (0, 0, 0))
    assert run(cond, seq) == [False] * 5  # B before A does not count
    seq = joints((0, 0, 0), (0, 1, 0), (1, 0, 0), (0, 1, 0))
    assert run(cond, seq) == [False, False, False, True]  # B again after A: done


def test_all_of_ordered_one_advance_per_step():
    cond = all_of([A, B, C], ordered=True)
    seq = joints((0, 0, 0), (1, 1, 1), (1, 1, 1), (1, 1, 1), (1, 1, 1))
    assert run(cond, seq) == [False, False, False, True, True]


def test_all_of_count_limits_the_set():
    one = all_of([A, B, C], ordered=True, count=1)
    assert run(one, joints((0, 0, 0), (1, 0, 0))) == [False, True]
    two = all_of([A, B, C], ordered=True, count=2)
    assert run(two, joints((0, 0, 0), (1, 0, 0), (0, 1, 0))) == [False, False, True]
    unordered = all_of([A, B, C], count=jnp.int32(2))
    assert run(unordered, joints((0, 0, 0), (1, 1, 0))) == [False, True]
    assert run(all_of([A, B, C]), joints((0, 0, 0), (1, 1, 0))) == [False, False]


def test_all_of_ordered_traced_count_under_vmap():
    cond_for = lambda n: all_of([A, B, C], ordered=True, count=n)  # noqa: E731
    seq = [make_obs(q=q).data for q in ((0, 0, 0), (1, 0, 0), (0, 1, 0), (0, 0, 1))]

    def final(n):
        cond = cond_for(n)
        obs = [Observation(d, LAYOUT, jnp.zeros(2, bool)) for d in seq]
        carry = cond.init(obs[0])
        mets = []
        for o in obs:
            carry, m = cond.step(carry, o)
            mets.append(m)
        return jnp.stack(mets)

    out = np.asarray(jax.jit(jax.vmap(final))(jnp.array([1, 2, 3])))
    assert out.tolist() == [[False, True, True, True], [False, False, True, True],
                            [False, False, False, True]]


def test_any_of():
    cond = AnyOf((A, B))
    assert run(cond, joints((0, 0, 0), (0, 0, 1), (0, 1, 0), (1, 0, 0))) == [
        False, False, True, True]


# ---- tasks ---------------------------------------------------------------------------------
def test_get_task_unknown_name_lists_valid_names():
    with pytest.raises(KeyError) as info:
        get_task("nope")
    message = str(info.value)
    assert "nope" in message
    for name in ("open_drawer", "push_buttons", "close_microwave", "lamp_on"):
        assert name in message


@pytest.mark.parametrize("name", list_tasks())
def test_descriptions_non_empty_for_every_variation(name):
    task = get_task(name)
    for v in range(task.num_variations):
        descriptions = task.descriptions(v)
        assert descriptions and all(isinstance(d, str) and d.strip() for d in descriptions)


@pytest.mark.parametrize("name, variation, first", [
    ("open_drawer", 0, "open the bottom drawer"),
    ("open_drawer", 2, "open the top drawer"),
    ("push_buttons", 0, "push the maroon button"),
    # spec: permutation index v // 3 of the 18 colours without red and lime,
    # count 1 + v % 3; permutation 1 = (maroon, green, navy), 16 = (maroon, blue, green).
    ("push_buttons", 2, "push the maroon button, then push the green button, "
                        "then push the blue button"),
    ("push_buttons", 4, "push the maroon button, then push the green button"),
    ("push_buttons", 5, "push the maroon button, then push the green button, "
                        "then push the navy button"),
    ("push_buttons", 49, "push the maroon button, then push the blue button"),
    ("close_microwave", 0, "close microwave"),
    ("lamp_on", 0, "turn on the light"),
    ("lamp_off", 0, "turn off the light"),
])
def test_first_description(name, variation, first):
    assert get_task(name).descriptions(variation)[0] == first


@pytest.mark.parametrize("name", task_params(list_tasks()))
def test_task_success_false_at_reset_true_after_expert(name):
    task = get_task(name)
    episodes = episodes_for(name)
    variations = np.array([0, task.num_variations - 1])
    env = episodes.reset(jax.random.split(jax.random.PRNGKey(0), 2), variations)
    assert (env.outcome == Outcome.RUNNING).all()
    for w, v in enumerate(variations):
        obs0 = jax.tree.map(lambda x, w=w: x[w], env.initial_obs)
        cond = task.success(jnp.int32(v))
        _, met = cond.step(cond.init(obs0), obs0)
        assert not bool(met), f"{name} v{v}: success already holds at reset"

    env = episodes.run_expert(env)
    labels = [Outcome(o).label for o in env.outcome]
    assert (env.outcome == Outcome.SUCCESS).all(), f"{name} {variations.tolist()}: {labels}"
    assert (env.key_actions >= 1).all() and (env.sim_steps > 0).all()


def test_registry_lists_the_benchmark_and_flags_missing_tasks():
    from agnostos_mjx.tasks import BENCHMARK, Split, is_implemented

    assert [len(BENCHMARK[s]) for s in Split] == [18, 13, 10]
    missing = [n for names in BENCHMARK.values() for n in names if not is_implemented(n)]
    for name in missing[:1]:
        with pytest.raises(KeyError, match="not implemented"):
            get_task(name)
    assert all(get_task(n).name == n for n in list_tasks())
