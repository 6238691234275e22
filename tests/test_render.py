"""CpuRenderer on a tiny scene: shapes, per-world state, colour overrides, camera errors.

WarpRenderer needs a CUDA GPU and is only checked for import safety here.
"""

from __future__ import annotations

import mujoco
import numpy as np
import pytest

from agnostos_mjx import render

XML = """
<mujoco>
  <visual><global offwidth="32" offheight="32"/></visual>
  <worldbody>
    <light pos="0 -0.5 2" dir="0 0.2 -1"/>
    <camera name="front" pos="0 -1 0.5" xyaxes="1 0 0 0 0.4 1"/>
    <camera name="top" pos="0 0 1.5"/>
    <geom name="table" type="box" pos="0 0 -0.02" size="0.6 0.6 0.02" rgba="0.6 0.6 0.6 1"/>
    <body name="cube" pos="0 0 0.1">
      <freejoint/>
      <geom name="red" type="box" size="0.08 0.08 0.08" rgba="1 0 0 1"/>
    </body>
    <body name="target" mocap="true" pos="0.3 0 0.1">
      <geom name="blue" type="box" size="0.08 0.08 0.08" rgba="0 0 1 1"
            contype="0" conaffinity="0"/>
    </body>
  </worldbody>
</mujoco>
"""
SIZE = 64


@pytest.fixture(scope="module")
def model() -> mujoco.MjModel:
    return mujoco.MjModel.from_xml_string(XML)


@pytest.fixture(scope="module")
def renderer(model: mujoco.MjModel):
    try:
        r = render.CpuRenderer(model, width=SIZE, height=SIZE)
    except RuntimeError as err:
        pytest.skip(f"no headless GL backend: {err}")
    with r:
        yield r


def _states(model: mujoco.MjModel) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """World 0: red cube centred, blue mocap aside. World 1: red cube far away, blue centred."""
    qpos = np.tile(model.qpos0, (2, 1))
    qpos[1, 0] = 5.0
    mocap_pos = np.array([[[0.3, 0.0, 0.1]], [[0.0, 0.0, 0.1]]])
    mocap_quat = np.tile([1.0, 0.0, 0.0, 0.0], (2, 1, 1))
    return qpos, mocap_pos, mocap_quat


def _centre(img: np.ndarray) -> np.ndarray:
    """Mean RGB of the central patch (where both cameras look at the origin)."""
    c = SIZE // 2
    return img[c - 4 : c + 4, c - 4 : c + 4].reshape(-1, 3).mean(axis=0)


def test_shapes_and_per_world_state(renderer: render.CpuRenderer, model: mujoco.MjModel) -> None:
    imgs = renderer.render(*_states(model), camera="front")
    assert imgs.shape == (2, SIZE, SIZE, 3) and imgs.dtype == np.uint8
    assert np.abs(imgs[0].astype(int) - imgs[1].astype(int)).mean() > 1.0
    r, g, b = _centre(imgs[0])
    assert r > 100 and r > 3 * g and r > 3 * b  # red cube in view
    r, g, b = _centre(imgs[1])
    assert b > 100 and b > 3 * r and b > 3 * g  # cube gone, mocap box moved in


def test_other_camera_differs(renderer: render.CpuRenderer, model: mujoco.MjModel) -> None:
    front = renderer.render(*_states(model), camera="front")
    top = renderer.render(*_states(model), camera="top")
    assert not np.array_equal(front, top)
    r, g, b = _centre(top[0])
    assert r > 3 * g and r > 3 * b


def test_geom_rgba_override(renderer: render.CpuRenderer, model: mujoco.MjModel) -> None:
    rgba0 = model.geom_rgba.copy()
    rgba = np.tile(model.geom_rgba, (2, 1, 1))
    rgba[0, mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_GEOM, "red")] = [0, 1, 0, 1]
    imgs = renderer.render(*_states(model), camera="front", geom_rgba=rgba)
    r, g, b = _centre(imgs[0])
    assert g > 100 and g > 3 * r and g > 3 * b
    np.testing.assert_array_equal(model.geom_rgba, rgba0)  # caller's model untouched
    again = renderer.render(*_states(model), camera="front")  # override not sticky
    assert _centre(again[0])[0] > 100


def test_mocap_defaults_and_bad_shapes(renderer: render.CpuRenderer, model: mujoco.MjModel) -> None:
    qpos, _, _ = _states(model)
    imgs = renderer.render(qpos[:1], None, None, camera="front")
    assert imgs.shape == (1, SIZE, SIZE, 3)
    with pytest.raises(ValueError, match="qpos"):
        renderer.render(qpos[:, :3], None, None, camera="front")


def test_unknown_camera(renderer: render.CpuRenderer, model: mujoco.MjModel) -> None:
    with pytest.raises(ValueError, match=r"front.*top"):
        renderer.render(*_states(model), camera="nope")


def test_close(model: mujoco.MjModel, renderer: render.CpuRenderer) -> None:
    r = render.CpuRenderer(model, width=SIZE, height=SIZE)
    with r:
        assert r.render(*_states(model), camera="top").shape == (2, SIZE, SIZE, 3)
    with pytest.raises(RuntimeError, match="closed"):
        r.render(*_states(model), camera="top")
    r.close()  # idempotent
    assert model.vis.global_.offwidth == 32  # buffer enlarged on the private copy only
    assert render.gl_backend() in ("egl", "osmesa", "glx", "glfw", "")
    assert hasattr(render, "WarpRenderer")  # defined without importing warp


def _batch(model: mujoco.MjModel, n: int = 5) -> tuple[np.ndarray, ...]:
    """n different worlds: cube and mocap box moved, colours changed per world."""
    rng = np.random.default_rng(0)
    qpos = np.tile(model.qpos0, (n, 1))
    qpos[:, :3] += rng.uniform(-0.2, 0.2, (n, 3))
    mocap_pos = np.tile([0.3, 0.0, 0.1], (n, 1, 1)) + rng.uniform(-0.1, 0.1, (n, 1, 3))
    mocap_quat = np.tile([1.0, 0.0, 0.0, 0.0], (n, 1, 1))
    rgba = np.tile(model.geom_rgba, (n, 1, 1))
    rgba[:, :, :3] = rng.uniform(0, 1, (n, model.ngeom, 3))
    return qpos, mocap_pos, mocap_quat, rgba


def _worker_threads(before: frozenset = frozenset()) -> list:
    """Render worker threads alive now, except `before` (renderers cached by earlier tests
    of the session keep theirs)."""
    import threading

    return [t for t in threading.enumerate()
            if t.name.startswith("cpu-render-") and t not in before]


def test_threaded_renderer_equals_single(model: mujoco.MjModel,
                                         renderer: render.CpuRenderer) -> None:
    qpos, pos, quat, rgba = _batch(model)
    flags = {"rgb": True, "depth": True, "segmentation": True}
    want = renderer.render_views(qpos, pos, quat, ("front", "top"), rgba, **flags)
    before = frozenset(_worker_threads())
    with render.ThreadedCpuRenderer(model, SIZE, SIZE, threads=3) as threaded:
        assert len(_worker_threads(before)) == 3
        for args in ((qpos, pos, quat, rgba), (qpos[:2], None, None, None)):
            got = threaded.render_views(*args[:3], ("front", "top"), args[3], **flags)
            ref = want if args[0] is qpos else renderer.render_views(
                *args[:3], ("front", "top"), None, **flags)
            for cam in ("front", "top"):
                for field in ("pos", "mat", "rgb", "depth", "segmentation"):
                    a, b = getattr(got[cam], field), getattr(ref[cam], field)
                    assert a.dtype == b.dtype and a.shape == b.shape
                    assert a.tobytes() == b.tobytes(), (cam, field)
        assert threaded.render(qpos, pos, quat, "top").shape == (5, SIZE, SIZE, 3)
        # Errors of the workers (and of the batch checks) reach the caller unchanged.
        for bad in (("nope",), ("front", "nope")):
            with pytest.raises(ValueError) as threaded_err:
                threaded.render_views(qpos, pos, quat, bad)
            with pytest.raises(ValueError) as single_err:
                renderer.render_views(qpos, pos, quat, bad)
            assert str(threaded_err.value) == str(single_err.value)
        with pytest.raises(ValueError, match=r"qpos must be \[B, 7\], got \(5, 3\)"):
            threaded.render_views(qpos[:, :3], None, None, ("front",))
        class Boom(Exception):
            pass

        def boom(*args, **kwargs):
            raise Boom("chunk failed")

        threaded._workers[1].renderer.render_views = boom  # an error inside one worker thread
        with pytest.raises(Boom, match="chunk failed"):
            threaded.render_views(qpos, pos, quat, ("front",))
        del threaded._workers[1].renderer.render_views
    assert _worker_threads(before) == []  # close() joined the threads
    with pytest.raises(RuntimeError, match="closed"):
        threaded.render_views(qpos, pos, quat, ("front",))
    threaded.close()  # idempotent


def test_render_threads_setting(model: mujoco.MjModel, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv(render.RENDER_THREADS_ENV, "1")
    assert render.render_threads() == 1
    before = frozenset(_worker_threads())
    r = render.cpu_renderer(model, SIZE, SIZE)
    assert isinstance(r, render.CpuRenderer) and _worker_threads(before) == []  # no threads for 1
    r.close()
    with render.ThreadedCpuRenderer(model, SIZE, SIZE) as one:  # one thread: no workers either
        assert one.threads == 1 and _worker_threads(before) == []
    monkeypatch.setenv(render.RENDER_THREADS_ENV, "2")
    with render.cpu_renderer(model, SIZE, SIZE) as two:
        assert isinstance(two, render.ThreadedCpuRenderer) and len(_worker_threads(before)) == 2
    monkeypatch.delenv(render.RENDER_THREADS_ENV)
    assert 1 <= render.render_threads() <= render.MAX_RENDER_THREADS
    monkeypatch.setenv(render.RENDER_THREADS_ENV, "many")
    with pytest.raises(ValueError, match=render.RENDER_THREADS_ENV):
        render.render_threads()
