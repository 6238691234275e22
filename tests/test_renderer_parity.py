"""The two renderers show the same scene alike (issue 51): tools/renderer_parity.py's metrics
and arguments, the OpenGL headlight rule that Warp copies (`headlight_as_light`), and, where
warp-lang is installed, both renderers on the reset states of all 41 tasks."""

from __future__ import annotations

import sys
from pathlib import Path
from types import SimpleNamespace

import mujoco
import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tools"))
import renderer_parity as rp  # noqa: E402

from agnostos_mjx.render.warp import HEADLIGHT_LIGHT, headlight_as_light  # noqa: E402
from agnostos_mjx.tasks import parse_task_names  # noqa: E402

SCENE = f"""
<mujoco>
  <visual>
    <global offwidth="32" offheight="32"/>
    <headlight ambient="0.45 0.45 0.45" diffuse="0.5 0.5 0.5" specular="0 0 0"/>
  </visual>
  <worldbody>
    <light name="top" pos="0 0 3" dir="0 0 -1" directional="true" diffuse="0.5 0.5 0.5"/>
    <light name="{HEADLIGHT_LIGHT}" directional="true" castshadow="false" active="false"/>
    <camera name="side" pos="1 0 0.3" xyaxes="0 1 0 -0.3 0 1"/>
    <camera name="top" pos="0 0 1.5"/>
    <geom name="table" type="box" pos="0 0 -0.02" size="0.6 0.6 0.02" rgba="0.8 0.7 0.5 1"/>
    <geom name="cube" type="box" pos="0 0 0.1" size="0.08 0.08 0.08" rgba="0.2 0.5 0.9 1"/>
  </worldbody>
</mujoco>
"""


def _images(rgb: np.ndarray, seg: np.ndarray, depth: np.ndarray) -> SimpleNamespace:
    return SimpleNamespace(rgb=rgb, segmentation=seg, depth=depth)


def test_compare_measures_rgb_segmentation_and_depth() -> None:
    rgb = np.full((1, 2, 2, 3), 100, np.uint8)
    seg = np.array([[[0, 1], [-1, 2]]])
    depth = np.full((1, 2, 2), 1.0, np.float32)
    warp_rgb = rgb.copy()
    warp_rgb[0, 0, 0] = (103, 100, 100)  # 3 of 12 channel values off by 1/255 each
    warp_depth = depth.copy()
    warp_depth[0, 0, 1] += 0.0004
    r = rp.compare("t", "c", _images(rgb, seg, depth), _images(warp_rgb, seg, warp_depth))
    assert r.rgb == pytest.approx(3 / 12)
    assert r.seg == r.seg_raw == 1.0
    assert r.depth_mm == pytest.approx(0.4 / 3, rel=1e-3)  # 3 pixels see a geom
    assert r.depth_max_mm == pytest.approx(0.4, rel=1e-3)
    assert r.broken() == []
    assert r.broken(max_rgb=0.1, max_depth_mm=0.1) == ["rgb 0.25 > 0.1", "depth 0.133 mm > 0.1"]


def test_coplanar_faces_of_one_body_count_as_alike() -> None:
    """Geoms 0 and 1 belong to body 5, geom 2 to body 6: a tie at the same depth between
    0 and 1 is alike, one between 0 and 2 or at another depth is not."""
    rgb = np.zeros((1, 1, 4, 3), np.uint8)
    depth = np.ones((1, 1, 4), np.float32)
    cpu = _images(rgb, np.array([[[0, 0, 0, 0]]]), depth)
    warp_depth = depth.copy()
    warp_depth[0, 0, 3] += 0.01
    warp = _images(rgb, np.array([[[0, 1, 2, 1]]]), warp_depth)
    r = rp.compare("t", "c", cpu, warp, geom_body=np.array([5, 5, 6]))
    assert r.seg_raw == 0.25 and r.seg == 0.5
    assert rp.compare("t", "c", cpu, warp).seg == 0.25  # without bodies only equal labels
    assert r.broken() == [f"seg 0.5000 < {rp.MIN_SEG}"]


def test_summary_and_table_show_the_worst_per_camera() -> None:
    rows = [rp.Parity("a", "front", 0.5, 2.0, 0.9995, 0.999, 0.1, 3.0),
            rp.Parity("b", "front", 2.5, 9.0, 0.9999, 0.9999, 0.01, 1.0)]
    worst = rp.summary(rows)["front"]
    assert worst["rgb"] == 2.5 and worst["seg"] == 0.9995 and worst["depth_max_mm"] == 3.0
    bounds = {"max_rgb": 2.0, "min_seg": 0.999, "max_depth_mm": 1.0}
    text = rp.table(rows, bounds).splitlines()
    assert len(text) == 1 + 2 + 1 + 1 and "2.50!" in text[2] and "!" not in text[1]


def test_arguments_quick_and_explicit() -> None:
    a = rp.parse_args(["--quick"])
    assert (a.task_names, a.size, a.worlds) == (list(rp.QUICK_TASKS), 64, 1)
    assert a.camera_names == rp.CAMERAS
    a = rp.parse_args(["--quick", "--size", "96", "--tasks", "lamp_on", "--cameras", "wrist"])
    assert (a.task_names, a.size, a.worlds, a.camera_names) == (["lamp_on"], 96, 1, ("wrist",))
    a = rp.parse_args(["--json=x.json", "--max-rgb", "3"])
    assert len(a.task_names) == 41 and a.size == 128 and a.json == "x.json" and a.max_rgb == 3
    for bad in (["--tasks", "no_such_task"], ["--size", "0"], ["--cameras", ","]):
        with pytest.raises(SystemExit) as err:
            rp.parse_args(bad)
        assert err.value.code == 2


def test_help_explains_every_flag(capsys) -> None:
    with pytest.raises(SystemExit):
        rp.parse_args(["--help"])
    out = capsys.readouterr().out
    for flag in ("--tasks", "--size", "--worlds", "--cameras", "--seed", "--quick", "--json",
                 "--max-rgb", "--min-seg", "--max-depth-mm", "Exit status"):
        assert flag in out


def test_headlight_becomes_the_placeholder_light() -> None:
    """Warp's copy: its own headlight off, the placeholder a directional light with the
    headlight's colours; the caller's model untouched; no placeholder, no change."""
    model = mujoco.MjModel.from_xml_string(SCENE)
    warp_model, light = headlight_as_light(model)
    assert light == 1 and warp_model is not model
    assert not warp_model.vis.headlight.active and model.vis.headlight.active
    assert warp_model.light_active.tolist() == [True, True]
    assert model.light_active.tolist() == [True, False]
    np.testing.assert_allclose(warp_model.light_ambient[1], 0.45, rtol=1e-6)
    np.testing.assert_allclose(warp_model.light_diffuse[1], 0.5, rtol=1e-6)
    np.testing.assert_allclose(warp_model.light_specular[1], 0.0)
    assert warp_model.light_type[1] == mujoco.mjtLightType.mjLIGHT_DIRECTIONAL
    bare = mujoco.MjModel.from_xml_string(SCENE.replace(f'name="{HEADLIGHT_LIGHT}"', 'name="x"'))
    assert headlight_as_light(bare) == (bare, -1)


def test_opengl_lights_every_camera_with_the_first_cameras_headlight() -> None:
    """The cause of issue 51: mjv_updateCamera moves the view, not the headlight, so a camera
    rendered after another keeps the first one's headlight; the inactive placeholder light
    changes nothing on the CPU."""
    from agnostos_mjx.render import CpuRenderer

    model = mujoco.MjModel.from_xml_string(SCENE)
    try:
        r = CpuRenderer(model, 32, 32, samples=0)
    except RuntimeError as err:
        pytest.skip(f"no headless GL backend: {err}")
    state = (model.qpos0[None], None, None)
    with r:
        alone = r.render_views(*state, ("top",))["top"].rgb
        after_side = r.render_views(*state, ("side", "top"))["top"].rgb
        side_first = r.render_views(*state, ("side", "top"))["side"].rgb
        side_alone = r.render_views(*state, ("side",))["side"].rgb
    assert np.abs(alone.astype(int) - after_side).mean() > 10
    np.testing.assert_array_equal(side_first, side_alone)
    without = mujoco.MjModel.from_xml_string(SCENE.replace(
        f'<light name="{HEADLIGHT_LIGHT}" directional="true" castshadow="false" active="false"/>',
        ""))
    assert without.nlight == 1
    with CpuRenderer(without, 32, 32, samples=0) as plain:
        np.testing.assert_array_equal(plain.render_views(*state, ("side", "top"))["top"].rgb,
                                      after_side)


@pytest.mark.slow
@pytest.mark.parametrize("task", parse_task_names("all"))
def test_both_renderers_show_the_reset_state_alike(task: str) -> None:
    """Every RLBench camera of a reset state of every task, CPU against Warp (warp-lang's CPU
    backend here), within issue 51's bounds.  Two choices of scenes/world.xml make that hold:
    the top light has no specular part (OpenGL lights per vertex and Warp per pixel, so a
    highlight differed; the wrist camera was 2-4/255 with it), and OpenGL tessellates
    spheres, capsules and cylinders finely (numslices / numstacks: the robot's outline
    flipped 0.15 % of a shoulder camera's pixels at the defaults)."""
    pytest.importorskip("warp")
    for r in rp.check_task(task, size=128, worlds=2, cameras=rp.CAMERAS):
        assert r.broken() == [], r
