"""Where observations render: the route chosen once from what the machine has, the run's
override, ended worlds left unrendered, and the timing policy's closed loop."""

from __future__ import annotations

import json
import logging
from dataclasses import replace
from pathlib import Path

import jax
import numpy as np
import pytest

from agnostos_mjx import eval as ev
from agnostos_mjx import physics
from agnostos_mjx.runtime import observation as ob
from agnostos_mjx.runtime.outcome import Outcome
from agnostos_mjx.tasks import SEEN, UNSEEN_LEVEL1, UNSEEN_LEVEL2

SIZE = 32


def test_auto_renders_on_the_gpu_wherever_warp_can(monkeypatch, caplog) -> None:
    monkeypatch.setattr(physics, "warp_available", lambda: True)
    assert physics.resolve_renderer("auto", "native") == "warp"
    assert physics.resolve_renderer("cpu", "native") == "cpu"
    monkeypatch.setattr(physics, "warp_available", lambda: False)
    monkeypatch.setattr(physics, "cuda_gpu", lambda: False)
    assert physics.resolve_renderer("auto", "native") == "cpu"
    assert physics.resolve_renderer("auto", "warp") == "warp"  # beside warp physics
    monkeypatch.setattr(physics, "cuda_gpu", lambda: True)  # a GPU without warp-lang
    physics._hint_once.cache_clear()
    with caplog.at_level(logging.WARNING, logger="agnostos_mjx.physics"):
        assert physics.resolve_renderer("auto", "native") == "cpu"
        assert physics.resolve_renderer("auto", "native") == "cpu"
    assert [r.getMessage() for r in caplog.records] == [physics.GPU_RENDERER_HINT]
    with pytest.raises(ValueError, match="unknown renderer 'gl'"):
        physics.resolve_renderer("gl")


def test_the_runs_renderer_overrides_the_specs(monkeypatch) -> None:
    from agnostos_mjx.runtime.observe import Observer

    monkeypatch.setattr(physics, "warp_available", lambda: False)
    spec = ob.ObservationSpec(renderer="warp")
    observer = Observer(None, None, "native", renderer="cpu")
    assert observer.route(spec) == physics.RENDER_ROUTES["cpu"]
    assert Observer(None, None, "native").route(spec).on_device
    assert not Observer(None, None, "native").route(ob.ObservationSpec()).on_device


def test_routes_say_what_they_offer() -> None:
    """Every route `--renderer` names offers what the layers above read: images on the
    device or on the host, a slow load to start early, a label for the log."""
    assert physics.RENDERERS == ("auto", *physics.RENDER_ROUTES)
    for name, route in physics.RENDER_ROUTES.items():
        assert route.name == name and route.label
    cpu, warp = physics.RENDER_ROUTES["cpu"], physics.RENDER_ROUTES["warp"]
    assert not cpu.on_device and not cpu.preload
    assert warp.on_device and warp.preload
    assert physics.render_route("warp") is warp
    assert physics.render_route("auto", "warp") is warp  # the renderer beside warp physics


@pytest.fixture(scope="module")
def lamp():
    from agnostos_mjx.runtime.env import Episodes
    from agnostos_mjx.tasks import get_task

    runner = Episodes(get_task("lamp_on"), "native", renderer="cpu")
    env = runner.reset(jax.random.split(jax.random.PRNGKey(3), 3), np.zeros(3, np.int32))
    return runner, env


def test_ended_worlds_are_not_rendered(lamp) -> None:
    """A world that has ended acts no more: blank images, no frame counted; the running
    worlds' pixels are those of a whole-batch render."""
    runner, env = lamp
    spec = ob.ObservationSpec(cameras=("front", "wrist"), height=SIZE, width=SIZE,
                              modalities=("rgb", "depth", "segmentation"), renderer="cpu")
    try:
        whole = runner.observe(env, spec)
    except RuntimeError as err:  # no headless GL
        pytest.skip(str(err))
    frames = runner.observer.frames
    ended = replace(env, outcome=np.array([Outcome.RUNNING, Outcome.SUCCESS, Outcome.RUNNING],
                                          np.int32))
    part = runner.observe(ended, spec)
    assert runner.observer.frames - frames == 2 * 2
    for name in spec.cameras:
        a, b = whole.cameras[name], part.cameras[name]
        for field in ("rgb", "depth", "segmentation", "extrinsics"):
            assert np.array_equal(getattr(a, field)[[0, 2]], getattr(b, field)[[0, 2]]), field
        assert not b.rgb[1].any() and (b.segmentation[1] == -1).all()
    assert runner.observer.render_s > 0


def test_timing_policy_runs_the_dense_loop_and_the_split_names_rendering(lamp, tmp_path: Path
                                                                         ) -> None:
    runner, env = lamp
    try:
        runner.observe(env, ob.ObservationSpec(height=SIZE, width=SIZE, renderer="cpu"))
    except RuntimeError as err:  # no headless GL
        pytest.skip(str(err))
    out = tmp_path / "run"
    code = ev.main(["--policy", "timing", "--policy-arg", "cameras=front,wrist",
                    "--policy-arg", f"size={SIZE}", "--policy-arg", "chunk=2",
                    "--action-mode", "dense", "--dense-steps", "6", "--tasks", "lamp_on",
                    "--seeds", "0", "--episodes", "2", "--batch", "2", "--renderer", "cpu",
                    "--quiet", "--out", str(out)])
    assert code == 0
    results = json.loads((out / "results.json").read_text())
    assert results["renderer"] == "cpu" and results["config"]["protocol"]["renderer"] == "cpu"
    assert results["policy"]["privileged"] is False
    records = [json.loads(x) for x in (out / "episodes.jsonl").read_text().splitlines()]
    assert [r["outcome"] for r in records] == ["max_steps", "max_steps"]
    (split,) = [line for line in map(json.loads, (out / "timings.jsonl").read_text()
                                     .splitlines()) if "task" in line]
    # asked every 2 of 6 control steps: 3 observations of 2 worlds x 2 cameras
    assert split["frames"] == 3 * 2 * 2 and split["render_s"] > 0
    assert split["rounds"] == 6


def test_timing_policy_refuses_a_bad_chunk() -> None:
    from agnostos_mjx.policies.timing import TimingOptions

    with pytest.raises(ValueError, match="chunk"):
        TimingOptions(chunk=0)


def test_dense_periods_scan_their_conditions_in_short_chunks() -> None:
    from agnostos_mjx.runtime.phase import CONDITION_ROWS, condition_rows

    assert [condition_rows(n) for n in (1, 8, 10, 16, 17, 1000)] == [8, 8, 16, 16, 32,
                                                                    CONDITION_ROWS]


def test_warp_preload_starts_once_and_is_waited_for(monkeypatch) -> None:
    """A run on the warp route loads Warp on one background thread (render.warp.preload),
    started once however often asked; a failed load is left to the renderer's own import."""
    import threading

    from agnostos_mjx.render import warp

    started = []
    release = threading.Event()

    def load() -> None:
        started.append(threading.current_thread().name)
        release.wait(5)

    monkeypatch.setattr(warp, "_load_warp", load)
    monkeypatch.setattr(warp, "_preloading", None)
    warp.preload()
    warp.preload()
    thread = warp._preloading
    assert thread is not None and thread.is_alive()
    release.set()
    thread.join(5)
    assert started == ["warp-preload"]


def test_a_smaller_batch_reuses_a_larger_warp_renderer() -> None:
    """A Warp render context has a fixed world count and costs seconds to build: a batch of
    fewer worlds (an export's retries, the last chunk) renders on the smallest one built
    for at least as many, its rows padded; nothing smaller is built."""
    from agnostos_mjx.infra.sharding import pad
    from agnostos_mjx.runtime.observe import Observer

    spec = ob.ObservationSpec(cameras=("front", "wrist"), height=SIZE, width=SIZE)
    observer = Observer(None, None, "native")
    assert observer._warp_worlds(spec, 24) == 24  # none built yet
    observer._renderers[Observer._warp_key(spec, 24)] = object()
    observer._renderers[Observer._warp_key(spec, 75)] = object()
    observer._renderers[Observer._warp_key(replace(spec, height=SIZE * 2, width=SIZE * 2),
                                           8)] = object()
    assert [observer._warp_worlds(spec, n) for n in (3, 24, 25, 75, 76)] == [24, 24, 75, 75, 76]
    x = np.arange(6.0).reshape(3, 2)
    padded = pad(x, 5)
    assert padded.shape == (5, 2) and (padded[:3] == x).all() and (padded[3:] == x[-1]).all()
    assert pad(x, 3) is x
    assert np.asarray(pad(jax.numpy.asarray(x), 4))[3].tolist() == [4.0, 5.0]


@pytest.mark.slow  # Warp's kernels build for its CPU backend (minutes on a fresh machine)
def test_padded_warp_observation_equals_the_direct_one() -> None:
    """On the Warp route (here on Warp's CPU backend, where warp-lang is installed) a
    sub-batch rendered on a larger context, padded, equals the full batch's rows: every
    modality of every camera, and no second context is built."""
    pytest.importorskip("warp")
    from agnostos_mjx.runtime.env import Episodes
    from agnostos_mjx.tasks import get_task

    runner = Episodes(get_task("lamp_on"), "native", renderer="warp")
    env = runner.reset(jax.random.split(jax.random.PRNGKey(0), 3), np.zeros(3, np.int32))
    spec = ob.ObservationSpec(cameras=("front", "wrist"), height=16, width=16,
                              modalities=("rgb", "depth", "point_cloud", "segmentation"))
    full = runner.observe(env, spec)
    part = runner.observe(jax.tree.map(
        lambda x: x[1:] if getattr(x, "ndim", 0) and x.shape[0] == 3 else x, env), spec)
    assert [k[-1] for k in runner.observer._renderers if k[0] == "warp"] == [3]
    for cam in spec.cameras:
        for field in ("rgb", "depth", "point_cloud", "segmentation", "extrinsics"):
            got = np.asarray(getattr(part.cameras[cam], field))
            assert got.shape[0] == 2
            np.testing.assert_array_equal(got, np.asarray(getattr(full.cameras[cam], field))[1:])


@pytest.mark.slow  # Warp's kernels build for its CPU backend (minutes on a fresh machine)
def test_ended_worlds_look_the_same_on_both_routes() -> None:
    """A world that has ended gets the same blank observation from MJX-Warp as from
    OpenGL (every modality and the camera pose); the running worlds keep their images."""
    pytest.importorskip("warp")
    from agnostos_mjx.runtime.env import Episodes
    from agnostos_mjx.tasks import get_task

    spec = ob.ObservationSpec(cameras=("front", "wrist"), height=16, width=16,
                              modalities=("rgb", "depth", "point_cloud", "segmentation"))
    obs = {}
    for route in ("warp", "cpu"):
        runner = Episodes(get_task("lamp_on"), "native", renderer=route)
        env = runner.reset(jax.random.split(jax.random.PRNGKey(0), 3), np.zeros(3, np.int32))
        ended = replace(env, outcome=np.array([Outcome.RUNNING, Outcome.SUCCESS,
                                               Outcome.RUNNING], np.int32))
        try:
            obs[route] = (runner.observe(env, spec), runner.observe(ended, spec))
        except RuntimeError as err:  # no headless GL
            pytest.skip(str(err))
        runner.close()
    for cam in spec.cameras:
        for field in ("rgb", "depth", "point_cloud", "segmentation", "extrinsics"):
            warp_whole, warp_part = (np.asarray(getattr(o.cameras[cam], field))
                                     for o in obs["warp"])
            cpu_part = np.asarray(getattr(obs["cpu"][1].cameras[cam], field))
            np.testing.assert_array_equal(warp_part[1], cpu_part[1], err_msg=f"{cam} {field}")
            np.testing.assert_array_equal(warp_part[[0, 2]], warp_whole[[0, 2]])
        assert np.asarray(obs["warp"][0].cameras[cam].rgb)[1].any()  # rendered while running


@pytest.mark.slow  # 41 scenes' render contexts (Warp's CPU backend where warp-lang is installed)
@pytest.mark.parametrize("name", sorted(SEEN + UNSEEN_LEVEL1 + UNSEEN_LEVEL2))
def test_every_task_renders_on_the_warp_route(name: str) -> None:
    """Each task's reset scene renders on MJX-Warp: the rope's and the groceries' scenes
    over 60 dofs included (MuJoCo Warp refused their dense Jacobian)."""
    pytest.importorskip("warp")
    from agnostos_mjx.runtime.env import Episodes
    from agnostos_mjx.tasks import get_task

    runner = Episodes(get_task(name), "native", renderer="warp")
    env = runner.reset(jax.random.split(jax.random.PRNGKey(0), 2), np.zeros(2, np.int32))
    obs = runner.observe(env, ob.ObservationSpec(cameras=("front", "wrist"), height=16,
                                                 width=16, modalities=("rgb", "depth")))
    runner.close()
    for cam in ("front", "wrist"):
        rgb, depth = np.asarray(obs.cameras[cam].rgb), np.asarray(obs.cameras[cam].depth)
        assert rgb.shape == (2, 16, 16, 3) and rgb.std() > 0, (name, cam)  # a scene, not blank
        assert np.isfinite(depth).all() and (depth > 0).all(), (name, cam)


@pytest.mark.parametrize("pinned", [None, True, False])
def test_to_numpy_through_pinned_memory_equals_device_get(pinned) -> None:
    """A numpy policy's images on the GPU route come through pinned host memory
    (infra.host_copy); every path gives device_get's numpy arrays, leaves that are not JAX
    arrays kept.  Here on the CPU, where None takes device_get and True the pinned path."""
    from agnostos_mjx.infra import host_copy

    tree = {"rgb": jnp_arange((2, 3, 4, 3), np.uint8), "depth": jnp_arange((2, 3, 4), np.float32),
            "none": None, "host": np.ones(2), "k": 3}
    assert not host_copy._pinned_here(tree["rgb"])  # CPU arrays: not worth the move
    out, ref = host_copy.to_numpy(tree, pinned), jax.device_get(tree)
    assert out.keys() == ref.keys() and out["none"] is None and out["k"] == 3
    for key in ("rgb", "depth", "host"):
        assert isinstance(out[key], np.ndarray) and out[key].dtype == ref[key].dtype
        np.testing.assert_array_equal(out[key], ref[key])


def jnp_arange(shape: tuple[int, ...], dtype: type) -> jax.Array:
    return jax.numpy.arange(int(np.prod(shape))).reshape(shape).astype(dtype)


def test_to_numpy_falls_back_when_pinned_memory_is_refused(monkeypatch, caplog) -> None:
    """A runtime that refuses the move to pinned memory costs one warning, then every copy
    takes device_get: the observation still arrives, equal."""
    import logging

    from agnostos_mjx.infra import host_copy

    def refuse(*_args, **_kw):
        raise RuntimeError("no pinned_host here")

    monkeypatch.setattr(host_copy, "_pinned_failed", False)
    monkeypatch.setattr(host_copy.jax, "device_put", refuse)
    x = jnp_arange((2, 3), np.uint8)
    with caplog.at_level(logging.WARNING, logger="agnostos_mjx.infra.host_copy"):
        for _ in range(2):
            np.testing.assert_array_equal(host_copy.to_numpy({"x": x}, pinned=True)["x"],
                                          np.asarray(x))
    assert len(caplog.records) == 1 and "no pinned_host here" in caplog.records[0].getMessage()
