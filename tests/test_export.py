"""Training-data export: 2 seen tasks x 2 demos in RLBench's episode folders, read back."""

from __future__ import annotations

import json

import numpy as np
import pytest

from agnostos_mjx.data import export as ex


def test_encodings_round_trip() -> None:
    depth = np.linspace(0.01, 4.5, 100).reshape(10, 10)
    np.testing.assert_allclose(ex.decode_depth(ex.encode_depth(depth, 0.01, 4.5), 0.01, 4.5),
                               depth, atol=1e-6)
    ids = np.arange(-1, 99).reshape(10, 10)
    assert np.array_equal(ex.rgb_to_int(ex.int_to_rgb(ids + 1)) - 1, ids)


def test_export_two_tasks_two_demos(tmp_path, capsys) -> None:
    cfg = ex.ExportConfig(out=tmp_path, tasks=("open_drawer", "push_buttons"), demos=2,
                          cameras=("front", "wrist"), size=32, batch=2)
    manifest = ex.export(cfg)
    assert "GB" in capsys.readouterr().out  # the estimate comes first
    for task in cfg.tasks:
        assert manifest["tasks"][task]["episodes"] == 2
        assert manifest["tasks"][task]["labels"]["objects"]
        for i in range(2):
            ep = ex.read_episode(ex.episode_dir(tmp_path, task, i))
            n = len(ep["low_dim"]["gripper_pose"])
            assert n >= 3  # reset + key actions
            assert ep["front_rgb"].shape == (n, 32, 32, 3) and ep["front_rgb"].dtype == np.uint8
            assert ep["wrist_depth"].shape == (n, 32, 32) and ep["wrist_mask"].dtype == np.int32
            assert 0.1 < np.median(ep["front_depth"]) < 4.5
            assert ep["low_dim"]["front_camera_extrinsics"].shape == (n, 4, 4)
            assert ep["low_dim"]["key_action"].shape == (n, 8)
            assert ep["descriptions"] and isinstance(ep["variation"], int)
    # Resumable: a rerun writes nothing; a damaged file is detected by its checksum.
    first = ex.episode_dir(tmp_path, "open_drawer", 0)
    stamp = (first / "SHA256SUMS").stat().st_mtime_ns
    ex.export(cfg)
    assert (first / "SHA256SUMS").stat().st_mtime_ns == stamp
    (first / "front_rgb" / "0.png").write_bytes(b"broken")
    with pytest.raises(ValueError, match="checksum"):
        ex.read_episode(first)
    assert json.loads((tmp_path / "manifest.json").read_text())["config"]["size"] == 32
