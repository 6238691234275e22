"""Served policies (openpi's websocket protocol) on loopback: wire format, adapter, the
remote oracle against the in-process one, faults that end only their episodes."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("websockets")  # the `serve` extra
pytest.importorskip("msgpack")

from agnostos_mjx import eval as ev  # noqa: E402
from agnostos_mjx.infra.gpu import memory_env  # noqa: E402
from agnostos_mjx.remote import wire  # noqa: E402
from agnostos_mjx.remote.adapter import (  # noqa: E402
    BadAnswer,
    make_adapter,
    parse_action,
)
from agnostos_mjx.sim.math3d import xyzw_to_axis_angle_f32  # noqa: E402

TASKS = "lamp_on,phone_on_base"  # a button and a pick-and-place (grasp state travels)
SAME = ("task", "seed", "episode", "variation", "success", "outcome", "key_actions",
        "sim_steps")


# ---- pure pieces ----------------------------------------------------------------------------
def test_wire_round_trip_and_openpi_layout() -> None:
    msg = {"a": np.arange(6, dtype=np.float32).reshape(2, 3), "b": np.uint8(7),
           "c": [np.zeros(2, bool), "text"], "d": {"e": np.float64(1.5)}}
    back = wire.unpackb(wire.packb(msg))
    assert back["a"].dtype == np.float32 and np.array_equal(back["a"], msg["a"])
    assert back["b"] == 7 and back["b"].dtype == np.uint8
    assert back["c"][1] == "text" and back["c"][0].dtype == bool
    assert back["d"]["e"] == 1.5
    import msgpack  # the raw layout, as openpi_client.msgpack_numpy writes it

    raw = msgpack.unpackb(wire.packb(np.ones(3, np.int16)))
    assert raw == {b"__ndarray__": True, b"data": np.ones(3, np.int16).tobytes(),
                   b"dtype": "<i2", b"shape": [3]}
    with pytest.raises(TypeError):
        wire.packb(np.array([object()]))


def test_parse_action_conventions() -> None:
    rlb = make_adapter("rlbench")
    pos, quat, grip = parse_action(rlb, {"actions": np.array([1, 2, 3, 0, 1, 0, 0, 1.0])})
    assert np.allclose(pos, [1, 2, 3]) and np.allclose(quat, [0, 0, 1, 0]) and grip == 1.0
    chunk = np.array([[0, 0, 0, 0, 0, 0, 1, 0], [4, 5, 6, 1, 0, 0, 0, 0.25]], np.float32)
    pos, quat, grip = parse_action(make_adapter("rlbench", action_index=1, quat_order="wxyz",
                                                gripper="closed"), {"actions": chunk})
    assert np.allclose(pos, [4, 5, 6]) and np.allclose(quat, [1, 0, 0, 0]) and grip == 0.75
    assert parse_action(rlb, {"actions": np.zeros((0, 8))}) is None  # nothing to execute
    for bad in ("garbage", {"action": [1]}, {"actions": np.zeros(5)},
                {"actions": np.full(8, np.nan)}, {"actions": "x"}, {"actions": np.zeros(8)}):
        with pytest.raises(BadAnswer):
            parse_action(rlb, bad)
    with pytest.raises(BadAnswer):
        parse_action(make_adapter("rlbench", action_index=2), {"actions": chunk})


def test_adapter_presets_keys_and_spec() -> None:
    assert make_adapter("sim").spec() is None  # nothing rendered for the reference server
    spec = make_adapter("libero").spec()
    assert spec.cameras == ("front", "wrist") and (spec.height, spec.width) == (224, 224)
    custom = make_adapter("droid", keys=json.dumps({"img": "overhead_rgb", "pc":
                                                     "front_point_cloud", "q": "joint_positions"}),
                          height=64, width=96)
    spec = custom.spec()
    assert spec.cameras == ("overhead", "front") and set(spec.modalities) == {"rgb",
                                                                              "point_cloud"}
    assert (spec.height, spec.width) == (64, 96)
    with pytest.raises(ValueError, match="unknown observation sources"):
        make_adapter("rlbench", keys={"x": "front_thermal"})
    with pytest.raises(ValueError, match="unknown preset"):
        make_adapter("aloha")
    half_turn_z = np.array([0.0, 0.0, 1.0, 0.0])  # xyzw
    assert np.allclose(xyzw_to_axis_angle_f32(half_turn_z), [0, 0, np.pi])
    assert np.allclose(xyzw_to_axis_angle_f32(np.array([0, 0, 0, 1.0])), 0)


def test_gpu_memory_env() -> None:
    local, remote = "ws://localhost:8000", "ws://gpu-box:8000"
    assert memory_env(None, [remote], {}) == {}
    assert memory_env(None, [local], {}) == {"XLA_PYTHON_CLIENT_PREALLOCATE": "true",
                                            "XLA_PYTHON_CLIENT_MEM_FRACTION": "0.35"}
    assert memory_env(None, ["http://127.0.0.1:8080/v1"], {})  # an LLM server counts too
    assert memory_env(0.0, [], {}) == {"XLA_PYTHON_CLIENT_PREALLOCATE": "false"}
    assert memory_env(None, [], {"AGNOSTOS_GPU_MEM_FRACTION": "0.5"})[
        "XLA_PYTHON_CLIENT_MEM_FRACTION"] == "0.5"
    assert memory_env(None, [local], {"XLA_PYTHON_CLIENT_MEM_FRACTION": ".2"}) == {}  # user's
    with pytest.raises(ValueError):
        memory_env(1.5, [], {})


# ---- end to end on loopback -----------------------------------------------------------------
@pytest.fixture(scope="module")
def oracle_server():
    from agnostos_mjx.policies import make_policy
    from agnostos_mjx.remote.server import PolicyServer

    with PolicyServer(make_policy("oracle")) as server:
        yield server


def _episodes(out: Path) -> list[dict]:
    records = [json.loads(line) for line in (out / "episodes.jsonl").read_text().splitlines()]
    return sorted(records, key=lambda r: (r["task"], r["seed"], r["episode"]))


def _run(out: Path, *args: str) -> int:
    return ev.main(["--tasks", TASKS, "--seeds", "0", "--batch", "4", "--quiet",
                    "--out", str(out), *args])


@pytest.mark.slow
def test_remote_oracle_equals_in_process_and_resumes(tmp_path: Path, oracle_server) -> None:
    assert _run(tmp_path / "local", "--policy", "oracle", "--episodes", "4") == 0
    remote = ["--policy", "remote", "--policy-url", oracle_server.url]
    # Two episodes, then --resume to four: the remote path records and resumes like any.
    assert _run(tmp_path / "remote", *remote, "--episodes", "2") == 0
    assert _run(tmp_path / "remote", *remote, "--episodes", "4", "--resume") == 0
    local, served = _episodes(tmp_path / "local"), _episodes(tmp_path / "remote")
    assert len(served) == 8
    assert [{k: r[k] for k in SAME} for r in served] == [{k: r[k] for k in SAME}
                                                         for r in local]
    assert all(r["success"] for r in local)
    results = json.loads((tmp_path / "remote" / "results.json").read_text())
    assert results["policy"]["name"] == "remote[oracle]"
    assert results["remote"]["failures"] == {} and results["remote"]["requests"] > 0


@pytest.mark.slow
def test_faults_end_only_their_episodes(tmp_path: Path, oracle_server, capfd) -> None:
    from agnostos_mjx.policies import make_policy
    from agnostos_mjx.remote.server import PolicyServer

    # Warm the served oracle (scene and jitted expert of lamp_on) so that the timeout
    # below measures the stall, not a first compilation on a loaded machine.
    assert ev.main(["--tasks", "lamp_on", "--seeds", "0", "--episodes", "1", "--quiet",
                    "--policy", "remote", "--policy-url", oracle_server.url,
                    "--out", str(tmp_path / "warm")]) == 0
    plan = {0: "drop", 1: "stall", 2: "garbage", 3: "error", 4: "no_actions"}

    def faults(obs: dict) -> str | None:
        state = obs["sim_state"]  # episode seed = seed * 100003 + episode; seed 0 here
        return plan.get(int(state["episode_seed"])) if state["key_actions"] == 1 else None

    with PolicyServer(make_policy("oracle"), faults=faults, stall_s=3600) as server:
        capfd.readouterr()
        code = ev.main(["--tasks", "lamp_on", "--seeds", "0", "--episodes", "7", "--batch", "7",
                        "--quiet", "--policy", "remote", "--policy-url", server.url,
                        "--policy-arg", "timeout_s=5", "--out", str(tmp_path / "faults")])
    out, err = capfd.readouterr()
    assert code == 0  # 5 of ~19 requests failed: not "mostly failed"
    assert "Traceback" not in out + err
    outcomes = {r["episode"]: r["outcome"] for r in _episodes(tmp_path / "faults")}
    assert outcomes == {0: "remote_error", 1: "remote_timeout", 2: "bad_remote_output",
                        3: "remote_error", 4: "bad_remote_output", 5: "success",
                        6: "success"}
    info = {r["episode"]: r["policy_info"] for r in _episodes(tmp_path / "faults")}
    assert "injected server fault" in info[3]["error"] and info[5] == {}
    assert "policy server" in out and "remote_timeout: 1" in out


def test_unreachable_server_is_a_usage_error(tmp_path: Path, capsys) -> None:
    import socket

    with socket.socket() as s:  # a port nobody listens on
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    code = ev.main(["--tasks", "lamp_on", "--policy", "remote", "--policy-url",
                    f"ws://127.0.0.1:{port}", "--policy-arg", "connect_timeout_s=2",
                    "--out", str(tmp_path / "x"), "--quiet"])
    assert code == 2 and "cannot reach the policy server" in capsys.readouterr().err
    assert ev.main(["--tasks", "lamp_on", "--policy", "remote", "--out",
                    str(tmp_path / "y"), "--quiet"]) == 2


def test_eval_caps_gpu_memory_for_a_local_server(monkeypatch, tmp_path: Path) -> None:
    import agnostos_mjx.infra.gpu as gpu

    calls = []
    monkeypatch.setattr(gpu, "apply_memory_limit", lambda f, urls: calls.append((f, urls)))
    # A usage error found after the cap (a variation lamp_on lacks) ends each run early.
    argv = ["--tasks", "lamp_on", "--variations", "99", "--out", str(tmp_path / "x"), "--quiet"]
    assert ev.main(["--policy", "remote", "--policy-url", "ws://localhost:1", *argv]) == 2
    assert ev.main(["--policy", "oracle", "--gpu-mem-fraction", "0.2", *argv]) == 2
    assert calls == [(None, ["ws://localhost:1"]), (0.2, [None])]
