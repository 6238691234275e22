"""A CPU run says nothing about warp-lang: mujoco-mjx's import prints 'Failed to import
warp' without it, and agnostos_mjx.physics.quiet_mjx (our one import of mjx) drops exactly
those lines."""

from __future__ import annotations

import subprocess
import sys
import textwrap

import pytest

# What a CPU evaluation imports (runtime -> the MJX backend), then a tiny MJX model built.
TINY_RUN = textwrap.dedent("""
    import mujoco
    import agnostos_mjx.runtime.env
    from agnostos_mjx.physics.mjx_backend import MjxBackend
    from agnostos_mjx.physics.quiet_mjx import mjx

    model = mujoco.MjModel.from_xml_string(
        '<mujoco><worldbody><body><freejoint/><geom size=".1"/></body></worldbody></mujoco>')
    backend = MjxBackend(model, impl="jax")
    data = mjx.make_data(backend.mx)
    print("nq", int(data.qpos.shape[0]))
""")


def test_mjx_import_prints_no_warp_complaint() -> None:
    run = subprocess.run([sys.executable, "-c", TINY_RUN], capture_output=True, text=True,
                         timeout=300)
    assert run.returncode == 0, run.stderr[-2000:]
    assert "Failed to import" not in run.stdout + run.stderr
    assert run.stdout == "nq 7\n"  # the program's own output still gets through


def test_with_warp_installed_stdout_is_left_alone() -> None:
    """With warp-lang there is no complaint to drop, and the import (often on the Warp
    loading thread) must not capture the process's stdout, which other threads print to."""
    pytest.importorskip("warp")
    code = textwrap.dedent("""
        import contextlib
        def capture(*args):
            raise AssertionError("stdout captured")
        contextlib.redirect_stdout = capture
        from agnostos_mjx.physics.quiet_mjx import mjx
        print("imported")
    """)
    run = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         timeout=300)
    assert run.returncode == 0, run.stderr[-2000:]
    assert run.stdout.endswith("imported\n")


def test_mesh_module_loads_when_mjx_jax_first_needs_it() -> None:
    """MJX's mesh module (trimesh, scipy.spatial) is not executed by the import, which the
    Warp route makes on its loading thread; MJX-jax's put_model of a scene with meshes
    still gets their convex hulls."""
    code = textwrap.dedent("""
        import sys
        import mujoco
        from agnostos_mjx.physics.quiet_mjx import mjx
        print("at import", "trimesh" in sys.modules, "scipy.spatial" in sys.modules)
        model = mujoco.MjModel.from_xml_string('''<mujoco>
          <asset><mesh name="t" vertex="0 0 0 1 0 0 0 1 0 0 0 1"/></asset>
          <worldbody><geom type="plane" size="1 1 .1"/>
            <body><freejoint/><geom type="mesh" mesh="t"/></body></worldbody></mujoco>''')
        hull = mjx.put_model(model, impl="jax")._impl.mesh_convex[0]
        print("after put_model", "trimesh" in sys.modules, len(hull.vert))
    """)
    run = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         timeout=300)
    assert run.returncode == 0, run.stderr[-2000:]
    assert run.stdout.splitlines()[-2:] == ["at import False False", "after put_model True 4"]
