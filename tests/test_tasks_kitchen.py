"""Unseen Level-2 tasks of the kitchen family: variation counts, verbatim
language (spec section per task) and each task's own success semantics,
checked on observations edited by hand (cheap: one reset per task)."""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from agnostos_mjx.runtime.env import Episodes
from agnostos_mjx.sim.observables import Observation
from agnostos_mjx.tasks import get_task


@functools.cache
def reset(name: str, variation: int = 0) -> tuple[Episodes, Observation]:
    """One world of `name` at reset: (episodes, its first observation)."""
    ep = Episodes(get_task(name), "native")
    env = ep.reset(jax.random.split(jax.random.PRNGKey(0), 1), np.array([variation]))
    return ep, jax.tree.map(lambda x: x[0], env.initial_obs)


def moved(obs: Observation, frame: str, pos, attached=None) -> Observation:
    """`obs` with `frame` moved to world position `pos` (and the grasp flags set)."""
    data = jnp.asarray(obs.data).at[obs.layout.slice(f"{frame}.pos")].set(jnp.asarray(pos, jnp.float32))
    flags = obs.attached if attached is None else jnp.asarray(attached)
    return Observation(data, obs.layout, flags)


def met(name: str, variation: int, obs0: Observation, obs: Observation) -> bool:
    cond = get_task(name).success(jnp.int32(variation))
    return bool(cond.step(cond.init(obs0), obs)[1])


@pytest.mark.parametrize("name, count", [("take_lid_off_saucepan", 1), ("unplug_charger", 1),
                                         ("take_usb_out_of_computer", 1),
                                         ("take_plate_off_colored_dish_rack", 3),
                                         ("turn_oven_on", 1)])
def test_variation_count(name, count):
    assert get_task(name).num_variations == count


@pytest.mark.parametrize("name, variation, expected", [
    ("take_lid_off_saucepan", 0, ["take lid off the saucepan",
                                  "using the handle, lift the lid off of the pan",
                                  "remove the lid from the pan",
                                  "grip the saucepan's lid and remove it from the pan",
                                  "leave the pan open", "uncover the saucepan"]),
    ("unplug_charger", 0, ["unplug charger", "take the charger out of the wall",
                           "grip the black charger and pull it out of its socket",
                           "slide the plug out from the wall", "remove the charger from the mains",
                           "get the charger from the wall plug"]),
    ("take_usb_out_of_computer", 0, [
        "take usb out of computer", "remove the usb stick from its port", "retrieve the usb stick",
        "grasp the usb stick and slide it out of the pc",
        "get a hold of the usb stick and pull it out of the desktop computer"]),
    ("take_plate_off_colored_dish_rack", 0, [
        "take plate off the black colored rack", "remove the dish from the black rack",
        "find the dish placed between the black spokes of the dish rack and drop it on the table",
        "grasp the plate from the black part of the dish rack, lift it up off of the rack, and "
        "leave it on the table top", "move the plate from the black rack to the table's surface",
        "lift the plate up off the black colored rack and drop it onto the table from a "
        "considerable height"]),
    ("turn_oven_on", 0, [
        "turn on the oven",
        "grip the left most knob on the oven and rotate it anti-clockwise to turn the oven on",
        "turn the left most knob on the oven to switch the oven on", "heat up the oven",
        "get the oven hot", "preheat the oven", "get the oven heat going"]),
])
def test_descriptions_verbatim(name, variation, expected):
    assert get_task(name).descriptions(variation) == expected


@pytest.mark.slow  # one per mechanism in the default suite; this task's compile in the slow group
def test_saucepan_lid_must_be_held_in_the_volume():
    name = "take_lid_off_saucepan"
    _, obs0 = reset(name)
    knob = "saucepan_lid_grasp_point"
    above = obs0.pos("saucepan_success")
    assert not met(name, 0, obs0, moved(obs0, knob, above, attached=[False]))  # lifted, dropped
    assert not met(name, 0, obs0, moved(obs0, knob, obs0.pos(knob), attached=[True]))  # held low
    assert met(name, 0, obs0, moved(obs0, knob, above, attached=[True]))
    # The lid rests on the rim at reset, 0.11 m below the volume's floor.
    assert 0.10 < float(above[2] - obs0.pos(knob)[2]) - 0.025 < 0.13


@pytest.mark.slow  # one per mechanism in the default suite; this task's compile in the slow group
def test_charger_held_by_its_pins_and_detected_once_pulled_out():
    from agnostos_mjx.sim.math3d import quat_conj, quat_rotate
    from agnostos_mjx.tasks.unplug_charger import CHARGER_POS

    name = "unplug_charger"
    _, obs0 = reset(name)
    local = quat_rotate(quat_conj(obs0.quat(name)), obs0.pos("charger") - obs0.pos(name))
    np.testing.assert_allclose(local, CHARGER_POS, atol=0.003)  # not fallen out at reset
    assert not met(name, 0, obs0, obs0)
    pulled = obs0.pos("charger_success")
    assert met(name, 0, obs0, moved(obs0, "charger", pulled))  # grasped or not


@pytest.mark.slow  # one per mechanism in the default suite; this task's compile in the slow group
def test_usb_must_leave_the_port_and_be_released():
    name = "take_usb_out_of_computer"
    _, obs0 = reset(name)
    assert not met(name, 0, obs0, obs0)  # plugged in, nothing held
    out = obs0.pos("usb") + jnp.array([0.0, 0.0, -0.2])  # fallen to the table
    assert not met(name, 0, obs0, moved(obs0, "usb", out, attached=[True]))  # still held
    assert met(name, 0, obs0, moved(obs0, "usb", out, attached=[False]))
    assert not met(name, 0, obs0, moved(obs0, "usb", obs0.pos("usb"), attached=[False]))


@pytest.mark.parametrize("variation, color, rows", [(0, "black", (0, 1)), (1, "red", (2, 3)),
                                                    (2, "purple", (4, 5))])
def test_plate_stands_between_the_named_rods(variation, color, rows):
    from agnostos_mjx.sim.math3d import quat_conj, quat_rotate

    name = "take_plate_off_colored_dish_rack"
    task = get_task(name)
    assert task.descriptions(variation)[0] == f"take plate off the {color} colored rack"
    ep, obs0 = reset(name, variation)
    root = name
    local = quat_rotate(quat_conj(obs0.quat(root)), obs0.pos("plate") - obs0.pos(root))
    model = ep.scene.model
    row_y = [float(model.geom(f"dish_rack_pillar{k}_a").pos[1]) for k in rows]
    assert min(row_y) < float(local[1]) < max(row_y)
    assert float(local[2]) > 0.11  # standing upright on the rack
    assert not met(name, variation, obs0, obs0)


def test_plate_must_be_on_the_block_off_the_rack_and_released():
    name = "take_plate_off_colored_dish_rack"
    _, obs0 = reset(name)
    goal = obs0.pos("success_target")
    on_block = obs0
    for i in range(5):  # the whole plate moves with its centre probe
        offset = obs0.pos(f"plate_probe{i}") - obs0.pos("plate_probe0")
        on_block = moved(on_block, f"plate_probe{i}", goal + offset + jnp.array([0, 0, 0.09]))
    assert met(name, 0, obs0, on_block)
    held = Observation(on_block.data, on_block.layout, jnp.asarray([True]))
    assert not met(name, 0, obs0, held)
    half_off = moved(on_block, "plate_probe3", obs0.pos("plate_probe3"))  # a rim point still in
    assert not met(name, 0, obs0, half_off)


@pytest.mark.slow  # one per mechanism in the default suite; this task's compile in the slow group
def test_oven_knob_is_the_left_most_and_needs_almost_a_quarter_turn():
    name = "turn_oven_on"
    ep, obs0 = reset(name)
    model = ep.scene.model
    knobs = [model.body(b).pos[1] for b in range(model.nbody)
             if model.body(b).name.startswith("oven_knob")]
    assert model.body("oven_knob").pos[1] == max(knobs)  # left-most seen from the front
    joint = model.joint("oven_knob_joint")
    np.testing.assert_allclose(joint.range, [0.0, np.pi / 2], atol=1e-6)
    door = ep.scene.initial_qpos[ep.scene.qpos_address["oven_door_joint"]]
    assert door == pytest.approx(np.pi / 2)  # closed, RLBench's convention

    def turned(angle):
        data = jnp.asarray(obs0.data).at[obs0.layout.slice("oven_knob_joint.q")].set(angle)
        return Observation(data, obs0.layout, obs0.attached)

    assert not met(name, 0, obs0, turned(1.45))
    assert met(name, 0, obs0, turned(1.55))
