"""Container tasks (close_jar, light_bulb_in, stack_cups, place_cups,
put_money_in_safe): variation counts, verbatim language, and the task-specific
parts of their success conditions on real reset observations."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from agnostos_mjx.runtime.env import Episodes
from agnostos_mjx.sim.observables import Observation
from agnostos_mjx.tasks import get_task, is_implemented
from tests.conftest import episodes_for


def needs(name: str):
    return pytest.mark.skipif(not is_implemented(name), reason=f"{name} not implemented")


def episodes(name: str) -> Episodes:
    return episodes_for(name)


def reset_obs(name: str, variation: int, seed: int = 0) -> Observation:
    """The settled observation of one world at reset."""
    env = episodes(name).reset(jax.random.split(jax.random.PRNGKey(seed), 1), np.array([variation]))
    return jax.tree.map(lambda x: x[0], env.initial_obs)


def moved(obs: Observation, frame: str, pos, attached=None) -> Observation:
    """`obs` with `frame` moved to `pos` (and the attach flags replaced)."""
    data = jnp.asarray(obs.data).at[obs.layout.slice(f"{frame}.pos")].set(jnp.asarray(pos, jnp.float32))
    return Observation(data, obs.layout, obs.attached if attached is None else
                       jnp.asarray(attached))


def met(task_name: str, variation: int, obs0: Observation, obs: Observation) -> bool:
    cond = get_task(task_name).success(jnp.int32(variation))
    return bool(cond.step(cond.init(obs0), obs)[1])


# ---- language and variation counts -----------------------------------------------------------
@pytest.mark.parametrize("name, count", [
    ("close_jar", 20), ("light_bulb_in", 20), ("stack_cups", 20), ("place_cups", 3),
    ("put_money_in_safe", 3),
])
def test_variation_count(name, count):
    if not is_implemented(name):
        pytest.skip(f"{name} not implemented")
    assert get_task(name).num_variations == count


@pytest.mark.parametrize("name, variation, expected", [
    ("close_jar", 0, ["close the red jar", "screw on the red jar lid",
                      "grasping the lid, lift it from the table and use it to seal the red jar",
                      "pick up the lid from the table and put it on the red jar"]),
    ("close_jar", 5, ["close the navy jar", "screw on the navy jar lid",
                      "grasping the lid, lift it from the table and use it to seal the navy jar",
                      "pick up the lid from the table and put it on the navy jar"]),
    ("close_jar", 19, ["close the white jar", "screw on the white jar lid",
                       "grasping the lid, lift it from the table and use it to seal the white jar",
                       "pick up the lid from the table and put it on the white jar"]),
    ("light_bulb_in", 0, ["screw in the red light bulb",
                          "screw the light bulb from the red holder into the lamp",
                          "pick up the light bulb from the red stand, lift it up to just above "
                          "the lamp, then screw it down into the lamp in a clockwise fashion",
                          "put the light bulb from the red casing into the lamp"]),
    ("light_bulb_in", 13, ["screw in the purple light bulb",
                           "screw the light bulb from the purple holder into the lamp",
                           "pick up the light bulb from the purple stand, lift it up to just "
                           "above the lamp, then screw it down into the lamp in a clockwise "
                           "fashion",
                           "put the light bulb from the purple casing into the lamp"]),
    ("stack_cups", 0, ["stack the other cups on top of the red cup",
                       "place two of the cups onto the odd cup out",
                       "put the remaining two cups on top of the red cup",
                       "pick up and set the cups down into the red cup",
                       "create a stack of cups with the red cup as its base",
                       "keeping the red cup on the table, stack the other two onto it"]),
    ("stack_cups", 11, ["stack the other cups on top of the orange cup",
                        "place two of the cups onto the odd cup out",
                        "put the remaining two cups on top of the orange cup",
                        "pick up and set the cups down into the orange cup",
                        "create a stack of cups with the orange cup as its base",
                        "keeping the orange cup on the table, stack the other two onto it"]),
    ("place_cups", 0, ["place 1 cup on the cup holder", "pick up one cup and put it on the mug tree",
                       "move 1 mug from the table to the cup holder",
                       "pick up one cup and slide its handle onto a spoke on the mug holder"]),
    ("place_cups", 1, ["place 2 cups on the cup holder", "pick up 2 cups and place them on the holder",
                       "move 2 cups from the table to the mug tree",
                       "pick up 2 mugs and slide their handles onto the cup holder spokes"]),
    ("place_cups", 2, ["place 3 cups on the cup holder", "pick up 3 cups and place them on the holder",
                       "move 3 cups from the table to the mug tree",
                       "pick up 3 mugs and slide their handles onto the cup holder spokes"]),
    ("put_money_in_safe", 0, ["put the money away in the safe on the bottom shelf",
                              "leave the money on the bottom shelf on the safe",
                              "place the stack of bank notes on the bottom shelf of the safe"]),
    ("put_money_in_safe", 2, ["put the money away in the safe on the top shelf",
                              "leave the money on the top shelf on the safe",
                              "place the stack of bank notes on the top shelf of the safe"]),
])
def test_descriptions_verbatim(name, variation, expected):
    if not is_implemented(name):
        pytest.skip(f"{name} not implemented")
    assert get_task(name).descriptions(variation) == expected


# ---- close_jar -------------------------------------------------------------------------------
@needs("close_jar")
@pytest.mark.parametrize("variation", [0, 1])
def test_close_jar_only_the_target_jar_counts_and_lid_must_be_released(variation):
    obs0 = reset_obs("close_jar", variation)
    target, other = (f"jar{variation % 2}", f"jar{1 - variation % 2}")
    on = lambda jar: np.asarray(obs0.pos(jar)) + np.array([0.0, 0.0, 0.0655])  # noqa: E731
    assert met("close_jar", variation, obs0, moved(obs0, "jar_lid0", on(target)))
    assert not met("close_jar", variation, obs0, moved(obs0, "jar_lid0", on(other)))
    held = moved(obs0, "jar_lid0", on(target), attached=[True])
    assert not met("close_jar", variation, obs0, held)


@pytest.mark.slow  # one test per task file in the default suite
@needs("close_jar")
def test_close_jar_target_colour_and_distinct_other_colour():
    ep = episodes("close_jar")
    variations = np.array([4, 7, 4, 7])
    env = ep.reset(jax.random.split(jax.random.PRNGKey(2), 4), variations)
    model = ep.scene.model
    from agnostos_mjx.sim.colors import COLORS

    for w, v in enumerate(variations):
        target, other = v % 2, 1 - v % 2
        rgb = env.geom_rgba[w, model.geom(f"jar{target}_body").id, :3]
        np.testing.assert_allclose(rgb, COLORS[v][1])
        assert not np.allclose(env.geom_rgba[w, model.geom(f"jar{other}_body").id, :3], rgb)


# ---- light_bulb_in ---------------------------------------------------------------------------
@pytest.mark.slow  # one per mechanism in the default suite; this task's compile in the slow group
@needs("light_bulb_in")
def test_light_bulb_in_clean_name_and_target_bulb():
    task = get_task("light_bulb_in")
    assert "bulb" in task.objects and "blub" not in task.objects  # X-ICM's typo fixed
    assert task.descriptions(2)[0] == "screw in the lime light bulb"
    for variation in (0, 1):
        obs0 = reset_obs("light_bulb_in", variation)
        socket = np.asarray(obs0.pos("light_bulb_in_success"))
        target, other = variation % 2, 1 - variation % 2
        assert met("light_bulb_in", variation, obs0, moved(obs0, f"bulb_phys{target}_base", socket))
        assert not met("light_bulb_in", variation, obs0,
                       moved(obs0, f"bulb_phys{other}_base", socket))
        # Still held: not yet screwed in.
        held = moved(obs0, f"bulb_phys{target}_base", socket, attached=[target == 0, target == 1])
        assert not met("light_bulb_in", variation, obs0, held)


# ---- stack_cups ------------------------------------------------------------------------------
@pytest.mark.slow  # one per mechanism in the default suite; this task's compile in the slow group
@needs("stack_cups")
def test_stack_cups_needs_both_cups_inside_the_base_cup():
    obs0 = reset_obs("stack_cups", 3)
    base = np.asarray(obs0.pos("cup2"))
    nested = base + np.array([0.0, 0.0, -0.07 + 0.035])  # a cup bottom nested in cup2
    on_rim = base + np.array([0.0, 0.0, 0.07])  # a cup bottom resting on cup2's rim
    both = moved(moved(obs0, "cup1_bottom", nested), "cup3_bottom", nested + [0, 0, 0.035])
    assert met("stack_cups", 3, obs0, both)
    assert not met("stack_cups", 3, obs0, moved(obs0, "cup1_bottom", nested))
    assert not met("stack_cups", 3, obs0, moved(both, "cup3_bottom", on_rim))
    assert not met("stack_cups", 3, obs0, moved(both, "cup1_bottom", nested, attached=[True, False]))


@pytest.mark.slow  # one per mechanism in the default suite; this task's compile in the slow group
@needs("stack_cups")
def test_stack_cups_base_cup_takes_the_variation_colour():
    from agnostos_mjx.sim.colors import COLORS

    ep = episodes("stack_cups")
    env = ep.reset(jax.random.split(jax.random.PRNGKey(4), 2), np.array([6, 18]))
    for w, v in enumerate((6, 18)):
        for k in (1, 2, 3):
            rgb = env.geom_rgba[w, ep.scene.model.geom(f"cup{k}_side0").id, :3]
            assert np.allclose(rgb, COLORS[v][1]) == (k == 2)


# ---- put_money_in_safe -----------------------------------------------------------------------
@pytest.mark.slow  # one per mechanism in the default suite; this task's compile in the slow group
@needs("put_money_in_safe")
def test_put_money_in_safe_only_the_named_shelf_counts():
    assert "shelf" not in get_task("put_money_in_safe").objects  # X-ICM's name for the safe
    obs0 = reset_obs("put_money_in_safe", 1)
    on = [np.asarray(obs0.pos(f"success_detector{k}")) + np.array([0.0, 0.0, 0.011])
          for k in range(3)]  # money resting on shelf k
    assert met("put_money_in_safe", 1, obs0, moved(obs0, "dollar_stack", on[1]))
    assert not met("put_money_in_safe", 1, obs0, moved(obs0, "dollar_stack", on[0]))
    assert not met("put_money_in_safe", 1, obs0, moved(obs0, "dollar_stack", on[2]))
    assert not met("put_money_in_safe", 1, obs0,
                   moved(obs0, "dollar_stack", on[1], attached=[True]))


# ---- place_cups ------------------------------------------------------------------------------
@needs("place_cups")
@pytest.mark.slow
def test_place_cups_counts_the_first_n_mugs_on_any_of_the_three_free_spokes():
    task = get_task("place_cups")
    assert "fourth cup" in task.objects and "forth cup" not in task.objects  # X-ICM's typo fixed
    obs0 = reset_obs("place_cups", 1)
    spoke = [np.asarray(obs0.pos(f"place_cups_holder_spoke{k}")) for k in range(4)]
    below = np.array([0.0, 0.0, -0.015])  # a hung mug's hole sits under its spoke
    two = moved(moved(obs0, "mug0_hole", spoke[2] + below), "mug1_hole", spoke[0] + below)
    assert met("place_cups", 1, obs0, two)
    assert met("place_cups", 0, obs0, two)
    assert not met("place_cups", 2, obs0, two)  # mug2 still on the table
    assert not met("place_cups", 1, obs0, moved(obs0, "mug0_hole", spoke[1] + below))
    # spoke3 carries the static fourth mug and has no sensor; a held mug does not count.
    assert not met("place_cups", 1, obs0, moved(two, "mug1_hole", spoke[3] + below))
    assert not met("place_cups", 1, obs0, moved(two, "mug1_hole", spoke[0] + below,
                                                 attached=[False, True, False]))
    assert not met("place_cups", 0, obs0, obs0)
