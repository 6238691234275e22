"""The record of what made a dataset's images (data/look.py): the scene version follows the
world's look and nothing else, check_look's one line, the RLBench export's manifest
record, and the gym env's warning with the option that renders as the data did."""

from __future__ import annotations

import json
import shutil
from dataclasses import replace
from pathlib import Path

import pytest

from agnostos_mjx.data import export as ex
from agnostos_mjx.data import export_run
from agnostos_mjx.data.look import LOOK_KEY, check_look, look_record, scene_version
from agnostos_mjx.sim.world import scenes_dir


def _scenes(tmp_path: Path, old: str = "", new: str = "") -> Path:
    """A copy of the scenes folder with `old` replaced by `new` in world.xml."""
    dest = tmp_path / f"scenes{len(list(tmp_path.iterdir()))}"
    shutil.copytree(scenes_dir(), dest)
    world = dest / "world.xml"
    text = world.read_text()
    assert text.count(old) == 1 or not old
    world.write_text(text.replace(old, new) if old else text)
    return dest


TOP_LIGHT = ('<light name="top" pos="0.2 0 3.0" dir="0 0 -1" directional="true" '
             'diffuse="0.5 0.5 0.5" specular="0 0 0"/>')


def test_scene_version_follows_the_look(tmp_path) -> None:
    base = scene_version()
    assert len(base) == 12 and int(base, 16) >= 0 and scene_version(scenes_dir()) == base
    assert scene_version(_scenes(tmp_path)) == base  # a copy: the same
    # comments and formatting are no part of the look
    note = ('<include file="panda.xml"/>', '<include file="panda.xml"/>\n\n  <!-- a note -->')
    assert scene_version(_scenes(tmp_path, *note)) == base
    changes = {  # a light's colour, direction or kind, the headlight, a camera, a colour
        "diffuse": (TOP_LIGHT, TOP_LIGHT.replace('diffuse="0.5 0.5 0.5"', 'diffuse="0.6 0.6 0.6"')),
        "dir": (TOP_LIGHT, TOP_LIGHT.replace('dir="0 0 -1"', 'dir="0.1 0 -1"')),
        "directional": (TOP_LIGHT, TOP_LIGHT.replace('directional="true"', 'directional="false"')),
        "specular": (TOP_LIGHT, TOP_LIGHT.replace('specular="0 0 0"', 'specular="0.3 0.3 0.3"')),
        "headlight": ('ambient="0.45 0.45 0.45"', 'ambient="0.4 0.4 0.4"'),
        "tessellation": ('numslices="48"', 'numslices="28"'),
        "camera": ('fovy="40"/>\n    <camera name="left_shoulder"',
                   'fovy="45"/>\n    <camera name="left_shoulder"'),
        "table": ('rgba="0.78 0.68 0.55 1"', 'rgba="0.7 0.68 0.55 1"'),
    }
    seen = {base}
    for what, (old, new) in changes.items():
        version = scene_version(_scenes(tmp_path, old, new))
        assert version not in seen, what
        seen.add(version)


def test_check_look() -> None:
    rec = look_record("cpu")
    assert rec == {"renderer": "cpu", "scene_version": scene_version(),
                   "package_version": rec["package_version"]}
    assert check_look({LOOK_KEY: rec}, "cpu") is None
    assert check_look({"codebase_version": "v3.0"}, "warp") is None  # no record: no warning
    for meta, renderer, parts in (
            ({LOOK_KEY: rec}, "warp", ["renderer cpu (here warp)"]),
            ({LOOK_KEY: {**rec, "scene_version": "0123456789ab"}}, "cpu",
             [f"scene version 0123456789ab (here {scene_version()})"]),
            ({LOOK_KEY: {**rec, "scene_version": "0123456789ab"}}, "warp",
             ["renderer cpu (here warp) and scene version 0123456789ab"])):
        text = check_look(meta, renderer)
        assert text and "\n" not in text and "slightly different images" in text, text
        for part in parts:
            assert part in text, (part, text)
    with pytest.raises(ValueError, match="route"):
        check_look({LOOK_KEY: rec}, "auto")


def test_rlbench_export_records_the_look(tmp_path, monkeypatch) -> None:
    """manifest.json at the export's root holds the record (tasks faked: the real export
    test checks it too); a rerun with another scene version refuses, as other settings do."""
    def fake_task(cfg, name, threads=None):
        return {"task": name, "skipped": 0, "written": 1, "failed": 0, "seconds": 0.0}

    monkeypatch.setattr(export_run, "_run_task", fake_task)
    cfg = ex.ExportConfig(out=tmp_path, tasks=("open_drawer",), demos=1)
    assert ex.export(cfg)[LOOK_KEY] == look_record(cfg.renderer) == look_record("cpu")
    manifest = json.loads((tmp_path / "manifest.json").read_text())
    assert manifest[LOOK_KEY] == look_record("cpu")
    assert check_look(manifest, "cpu") is None and check_look(manifest, "warp")
    ex.export(cfg)  # the same look: resumes
    manifest[LOOK_KEY]["scene_version"] = "0123456789ab"
    (tmp_path / "manifest.json").write_text(json.dumps(manifest))
    with pytest.raises(ValueError, match="scene_version 0123456789ab, not"):
        ex.export(cfg)
    manifest[LOOK_KEY] = look_record("cpu")
    (tmp_path / "manifest.json").write_text(json.dumps(manifest))
    with pytest.raises(ValueError, match="renderer cpu, .*not renderer warp"):  # another look
        ex.export(replace(cfg, renderer="warp"))


def test_export_renders_where_the_evaluator_does(tmp_path, monkeypatch) -> None:
    """--renderer auto takes the machine's route (physics.resolve_renderer, as the
    evaluator's); the route reaches the config, whose look record names it."""
    seen = {}

    def fake_export(cfg, workers):
        seen["renderer"] = cfg.renderer
        return {"wall_s": 0.0}

    monkeypatch.setattr(ex, "export", fake_export)
    monkeypatch.setattr(ex, "resolve_renderer", lambda name: "warp" if name == "auto" else name)
    assert ex.main(["--out", str(tmp_path), "--tasks", "open_drawer", "--demos", "1",
                    "--quiet"]) == 0
    assert seen["renderer"] == "warp"
    assert ex.main(["--out", str(tmp_path), "--tasks", "open_drawer", "--demos", "1",
                    "--renderer", "cpu", "--quiet"]) == 0
    assert seen["renderer"] == "cpu"
    with pytest.raises(ValueError, match="renderer must be cpu or warp"):
        ex.ExportConfig(out=tmp_path, tasks=("open_drawer",), renderer="auto")


def test_env_look_warning_names_the_renderer_option() -> None:
    pytest.importorskip("gymnasium")
    from agnostos_mjx.gym_env import EnvOptions, look_warning

    info = {LOOK_KEY: look_record("cpu")}
    assert look_warning(info, EnvOptions(renderer="cpu")) is None
    assert look_warning(None, EnvOptions(renderer="warp")) is None
    assert look_warning({"features": {}}, EnvOptions(renderer="warp")) is None
    text = look_warning(info, EnvOptions(renderer="warp"), renderer_flag="--env.renderer")
    assert text.endswith("; --env.renderer=cpu renders as the data was") and "\n" not in text
