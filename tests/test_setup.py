"""Process set-up: importing the package changes nothing, every command sets up JAX itself
(agnostos_mjx.infra.settings.configure_jax), the environment variables are the documented ones,
and the console scripts resolve."""

from __future__ import annotations

import importlib.util
import json
import os
import re
import subprocess
import sys
import textwrap
from importlib.metadata import entry_points
from pathlib import Path

import pytest

from agnostos_mjx.infra import settings

REPO = Path(__file__).resolve().parents[1]
PACKAGE = REPO / "agnostos_mjx"
LEVEL = settings.CPU_OPTIMISATION_FLAG
GPU_PLUGIN = importlib.util.find_spec("jax_plugins") is not None

# The command-line modules that run JAX: each calls configure_jax first thing in main().
COMMANDS = (
    "agnostos_mjx.eval", "agnostos_mjx.warmup", "agnostos_mjx.data.export",
    "agnostos_mjx.data.generate", "agnostos_mjx.serve", "agnostos_mjx.bench.backends",
    "agnostos_mjx.bench.observation", "agnostos_mjx.bench.dynamics", "agnostos_mjx.bench.remote_policy",
    "agnostos_mjx.evaluation.experts_check", "agnostos_mjx.xicm.build_memory", "agnostos_mjx.train.vla",
    "agnostos_mjx.train.vla_data", "agnostos_mjx.train.autoencoder", "agnostos_mjx.train.dynamics",
    "agnostos_mjx.train.evaluate", "agnostos_mjx.train.export", "agnostos_mjx.train.sampling_steps",
)
SCRIPTS = {"agnostos-eval": "agnostos_mjx.eval:cli",
           "agnostos-export": "agnostos_mjx.data.export:main",
           "agnostos-warmup": "agnostos_mjx.warmup:main",
           "agnostos-compare": "agnostos_mjx.compare:main"}


def _child(code: str, tmp_path: Path) -> dict:
    """Run `code` in a fresh Python without XLA_FLAGS or the cache's JAX variables (which
    this process's configure_jax set: conftest.py); its last stdout line as JSON."""
    env = {k: v for k, v in os.environ.items()
           if k not in ("XLA_FLAGS", "AGNOSTOS_XLA_TUNE") and not k.startswith("JAX_")}
    env.update(AGNOSTOS_JAX_CACHE=str(tmp_path / "jax"), PYTHONPATH=str(REPO))
    proc = subprocess.run([sys.executable, "-c", textwrap.dedent(code)], cwd=REPO, env=env,
                          capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr[-3000:]
    return json.loads(proc.stdout.strip().splitlines()[-1])


def test_import_has_no_side_effects(tmp_path: Path) -> None:
    out = _child("""
        import json, os, sys
        import agnostos_mjx
        bare = "jax" in sys.modules
        import agnostos_mjx.eval  # the launcher of --local-processes: it checks task names
        launcher = "jax" in sys.modules
        import agnostos_mjx.data.generate, jax
        print(json.dumps({"bare_imports_jax": bare, "eval_imports_jax": launcher,
                          "flags": os.environ.get("XLA_FLAGS"),
                          "cache": jax.config.jax_compilation_cache_dir}))
    """, tmp_path)
    assert out == {"bare_imports_jax": False, "eval_imports_jax": False, "flags": None,
                   "cache": None}


def test_every_command_sets_up_jax_before_anything_else(tmp_path: Path) -> None:
    """Each command's main, stopped at its argument parsing (--help), has set the flags and
    the compile cache already: what `python -m agnostos_mjx.eval` applied at import before."""
    out = _child(f"""
        import contextlib, io, json, os, runpy, sys
        import jax
        seen = {{}}
        for module in {COMMANDS!r}:
            os.environ.pop("XLA_FLAGS", None)
            jax.config.update("jax_compilation_cache_dir", None)
            sys.argv = [module, "--help"]
            with contextlib.redirect_stdout(io.StringIO()), contextlib.suppress(SystemExit):
                runpy.run_module(module, run_name="__main__", alter_sys=True)
            seen[module] = [os.environ.get("XLA_FLAGS"), jax.config.jax_compilation_cache_dir]
        print(json.dumps(seen))
    """, tmp_path)
    expected = [None if GPU_PLUGIN else LEVEL, str(tmp_path / "jax")]
    assert out == {module: expected for module in COMMANDS}


def test_configure_jax_before_jax_imports_no_jax(tmp_path: Path) -> None:
    """Called before JAX is imported (every command's main), configure_jax imports no JAX:
    the cache goes through JAX's environment variables, read when JAX is imported, so the
    launcher of --local-processes, which runs no JAX, starts its processes sooner."""
    out = _child("""
        import json, sys
        from agnostos_mjx.infra import settings
        settings.configure_jax()
        imported = "jax" in sys.modules
        import jax
        print(json.dumps({"imported": imported,
                          "cache": jax.config.jax_compilation_cache_dir,
                          "min_s": jax.config.jax_persistent_cache_min_compile_time_secs}))
    """, tmp_path)
    assert out == {"imported": False, "cache": str(tmp_path / "jax"), "min_s": 0}
    # AGNOSTOS_JAX_CACHE=off drops a cache directory inherited from a parent's set-up.
    off = _child("""
        import json, os
        os.environ.update(AGNOSTOS_JAX_CACHE="off", JAX_COMPILATION_CACHE_DIR="/elsewhere")
        from agnostos_mjx.infra import settings
        settings.configure_jax()
        import jax
        print(json.dumps({"cache": jax.config.jax_compilation_cache_dir}))
    """, tmp_path)
    assert off == {"cache": None}


@pytest.fixture
def no_cache(monkeypatch: pytest.MonkeyPatch) -> None:
    """configure_jax without touching this process's compile cache."""
    monkeypatch.setattr(settings, "enable_compilation_cache", lambda: None)
    monkeypatch.delenv("XLA_FLAGS", raising=False)
    monkeypatch.delenv("AGNOSTOS_XLA_TUNE", raising=False)


@pytest.mark.parametrize(("plugin", "cpu", "tune", "flags", "expected"), [
    (False, False, None, None, LEVEL),
    (True, False, None, None, None),  # a GPU install keeps XLA's default level
    (True, True, None, None, LEVEL),  # ... but not in a process that keeps JAX on the CPU
    (False, False, "0", None, None),
    (False, False, None, "--xla_backend_optimization_level=3", "--xla_backend_optimization_level=3"),
    (False, False, None, "--xla_dump_to=x", f"--xla_dump_to=x {LEVEL}"),
])
def test_cpu_optimisation_level(no_cache, monkeypatch: pytest.MonkeyPatch, plugin: bool,
                                cpu: bool, tune: str | None, flags: str | None,
                                expected: str | None) -> None:
    real = importlib.util.find_spec
    monkeypatch.setattr(importlib.util, "find_spec", lambda name, *a: (
        (object() if plugin else None) if name == "jax_plugins" else real(name, *a)))
    if tune is not None:
        monkeypatch.setenv("AGNOSTOS_XLA_TUNE", tune)
    if flags is not None:
        monkeypatch.setenv("XLA_FLAGS", flags)
    settings.configure_jax(cpu=cpu)
    settings.configure_jax(cpu=cpu)  # again: no change
    assert os.environ.get("XLA_FLAGS") == expected


@pytest.mark.parametrize(("setting", "value", "message"), [
    (settings.XLA_TUNE, "no", "AGNOSTOS_XLA_TUNE must be 0 or 1"),
    (settings.RENDER_THREADS, "many", "AGNOSTOS_RENDER_THREADS must be an integer"),
    (settings.GPU_MEM_FRACTION, "half", "AGNOSTOS_GPU_MEM_FRACTION must be a number"),
])
def test_bad_values_name_the_variable(monkeypatch: pytest.MonkeyPatch, setting: settings.Setting,
                                      value: str, message: str) -> None:
    monkeypatch.setenv(setting.name, value)
    read = {settings.XLA_TUNE: lambda: setting.get_switch(True),
            settings.RENDER_THREADS: setting.get_int,
            settings.GPU_MEM_FRACTION: setting.get_float}[setting]
    with pytest.raises(ValueError, match=message):
        read()


def test_the_package_reads_only_documented_variables() -> None:
    documented = {s.name for s in settings.SETTINGS}
    used = {name for path in PACKAGE.rglob("*.py")
            for name in re.findall(r"AGNOSTOS_[A-Z0-9_]+", path.read_text())}
    assert used <= documented, f"undocumented: {sorted(used - documented)}"
    assert all(s.doc for s in settings.SETTINGS)


def test_console_scripts_resolve() -> None:
    """The installed entry points (``pip install -e .`` refreshes them) load their mains."""
    scripts = {ep.name: ep for ep in entry_points(group="console_scripts")
               if ep.name.startswith("agnostos-")}
    assert {name: ep.value for name, ep in scripts.items()} == SCRIPTS
    for ep in scripts.values():
        assert callable(ep.load())


@pytest.mark.parametrize("script", [
    "agnostos-eval", "agnostos-export", "agnostos-warmup", "agnostos-compare"])
def test_usage_and_errors_name_the_command_typed(script: str, monkeypatch: pytest.MonkeyPatch,
                                                 capsys: pytest.CaptureFixture) -> None:
    """A console script's usage and error lines name the script; run as ``python -m`` (its
    file in sys.argv[0]), the module."""
    from agnostos_mjx.infra.cli import prog

    module = SCRIPTS[script].split(":")[0]
    main = next(iter(entry_points(group="console_scripts", name=script))).load()
    monkeypatch.setattr(sys, "argv", [f"/venv/bin/{script}", "--no-such-option"])
    with pytest.raises(SystemExit) as stop:
        main()
    err = capsys.readouterr().err
    assert stop.value.code == 2
    assert err.startswith(f"usage: {script} ") and f"\n{script}: error: " in err
    monkeypatch.setattr(sys, "argv", [f"/repo/{module.replace('.', '/')}.py"])
    assert prog(module) == f"python -m {module}"


def test_native_physics_threads_follow_the_cpu_affinity(monkeypatch: pytest.MonkeyPatch) -> None:
    """A process pinned to some cores (taskset, a container's cpuset) runs that many
    physics threads, not one per core of the machine."""
    import mujoco

    from agnostos_mjx.physics.native import NativeBackend

    monkeypatch.setattr(os, "sched_getaffinity", lambda pid: {0, 2, 5})
    assert settings.usable_cores() == 3
    model = mujoco.MjModel.from_xml_string("<mujoco><worldbody/></mujoco>")
    assert NativeBackend(model).nthread == 3
    monkeypatch.delattr(os, "sched_getaffinity")
    assert settings.usable_cores() == (os.cpu_count() or 1)
