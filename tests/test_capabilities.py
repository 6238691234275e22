"""Backends declare what they offer (physics.CAPABILITIES), and the layers above read that
instead of comparing names: a new backend's entry alone sets its renderer and loop."""

from __future__ import annotations

from types import SimpleNamespace

import mujoco
import numpy as np
import pytest

from agnostos_mjx import physics
from agnostos_mjx.physics import BACKENDS, CAPABILITIES, Capabilities
from agnostos_mjx.runtime.env import Episodes
from agnostos_mjx.runtime.phase import steps_per_iteration

TINY = "<mujoco><worldbody><body><freejoint/><geom size='0.1'/></body></worldbody></mujoco>"


def test_every_backend_but_auto_declares_its_capabilities() -> None:
    assert set(BACKENDS) - {"auto"} == set(CAPABILITIES)
    assert all(isinstance(c, Capabilities) for c in CAPABILITIES.values())


@pytest.mark.parametrize("name", [*CAPABILITIES, "new"])
def test_renderer_and_loop_follow_the_capabilities(name: str, monkeypatch) -> None:
    monkeypatch.setitem(CAPABILITIES, "new", Capabilities(
        on_device=True, padded_batch=True, steps_per_iteration=8, renderer="warp"))
    monkeypatch.setattr(physics, "warp_available", lambda: False)
    monkeypatch.setattr(physics, "cuda_gpu", lambda: False)
    caps = CAPABILITIES[name]
    assert physics.resolve_renderer("auto", name) == (caps.renderer or "cpu")
    assert physics.resolve_renderer("cpu", name) == "cpu"
    assert steps_per_iteration(name) == caps.steps_per_iteration


@pytest.mark.parametrize("padded", [False, True])
def test_padded_backends_settle_again_at_the_full_batch(padded: bool) -> None:
    runner = SimpleNamespace(capabilities=Capabilities(on_device=padded, padded_batch=padded))
    rows = Episodes._padded_rows(runner, np.array([1, 3]), 5)
    assert rows.tolist() == ([1, 3, 1, 3, 1] if padded else [1, 3])


def test_backend_objects_carry_their_capabilities() -> None:
    model = mujoco.MjModel.from_xml_string(TINY)
    assert physics.make_backend("native", model, threads=1).capabilities is CAPABILITIES["native"]
    assert physics.make_backend("jax", model).capabilities is CAPABILITIES["jax"]
