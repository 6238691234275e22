"""Transports and presets of served policies: rotation layouts of action rows (against
scipy), X-ICM's request and answer (preset xicm), chunks run as several key actions
(execute=K), OpenVLA's HTTP json_numpy protocol (preset openvla, deltas) with the same
failure outcomes as the websocket client."""

from __future__ import annotations

import json
import socket
import warnings
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from agnostos_mjx import eval as ev
from agnostos_mjx.remote import json_wire
from agnostos_mjx.remote.adapter import (
    BadAnswer,
    apply_row,
    lowdim,
    make_adapter,
    parse_action,
    parse_rows,
)
from agnostos_mjx.sim import math3d

Rotation = pytest.importorskip("scipy.spatial.transform").Rotation

XICM_KEYS = {"observation/front_image", "observation/wrist_image",
             "observation/overhead_image", "observation/state", "prompt"}
SAME = ("task", "seed", "episode", "variation", "success", "outcome", "key_actions",
        "sim_steps")


def wxyz(xyzw: np.ndarray) -> np.ndarray:
    return np.asarray(xyzw)[..., [3, 0, 1, 2]]


def same_rotation(a: np.ndarray, b: np.ndarray, tol: float = 1e-12) -> bool:
    """Two quaternion arrays (..., 4) name the same rotations (q and -q alike)."""
    return bool(np.all(np.abs(np.abs(np.sum(a * b, axis=-1)) - 1.0) < tol))


# ---- rotation conversions -----------------------------------------------------------------
def test_rotation_conversions_match_scipy() -> None:
    rot = Rotation.random(3000, random_state=7)
    q = wxyz(rot.as_quat())
    euler = rot.as_euler("xyz")
    assert np.allclose(math3d.quat_to_euler_xyz(q), euler, rtol=0, atol=1e-12)
    assert np.allclose(math3d.quat_to_euler_xyz(-q), euler, rtol=0, atol=1e-12)
    assert same_rotation(math3d.euler_xyz_to_quat(euler), q)
    rotvec = rot.as_rotvec()
    assert np.allclose(math3d.quat_to_rotvec(q), rotvec, rtol=0, atol=1e-12)
    assert same_rotation(math3d.rotvec_to_quat(rotvec), q)
    tiny = np.array([[1e-9, -2e-9, 3e-9], [4e-4, 0, -1e-4], [0, 0, 0]])
    assert np.allclose(math3d.rotvec_to_quat(tiny),
                       wxyz(Rotation.from_rotvec(tiny).as_quat()), rtol=0, atol=1e-15)
    assert np.allclose(math3d.quat_to_rotvec(math3d.rotvec_to_quat(tiny)), tiny, atol=1e-15)
    mats = rot.as_matrix()
    d6 = math3d.mat_to_rot6d(mats)
    assert np.array_equal(d6, np.concatenate([mats[:, :, 0], mats[:, :, 1]], axis=-1))
    # not orthonormal on input: Gram-Schmidt recovers the rotation
    skewed = np.concatenate([2.5 * mats[:, :, 0], mats[:, :, 1] + 0.3 * mats[:, :, 0]], -1)
    assert np.allclose(math3d.rot6d_to_mat(skewed), mats, atol=1e-12)
    # gimbal lock and RLBench's tip pointing down (angles at +-pi), as scipy gives them
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # scipy warns about the gimbal lock
        edge = np.array([[0.3, np.pi / 2, 0.0], [-0.4, -np.pi / 2, 0.0]])
        locked = Rotation.from_euler("xyz", edge).as_quat()
        assert np.allclose(math3d.quat_to_euler_xyz(wxyz(locked)),
                           Rotation.from_quat(locked).as_euler("xyz"), atol=1e-12)
    down = np.array([[0, 1, 0, 0.0], [1e-8, 1, 0, 0], [0, 0.9999, 0.01, 0], [0, 1, 0, 1e-9]])
    assert np.array_equal(np.sign(math3d.quat_to_euler_xyz(wxyz(down))),
                          np.sign(Rotation.from_quat(down).as_euler("xyz")))
    assert np.allclose(math3d.quat_to_euler_xyz(wxyz(down)),
                       Rotation.from_quat(down).as_euler("xyz"), atol=1e-12)


# ---- action rows --------------------------------------------------------------------------
def test_rows_of_every_rotation_parse_to_the_quaternion_rows_pose() -> None:
    rng = np.random.default_rng(3)
    rot = Rotation.random(5, random_state=11)
    pos = rng.uniform(-0.5, 1.5, (5, 3))
    grip = np.array([0.0, 1.0, 0.3, 0.7, 1.0])
    quat_rows = np.concatenate([pos, rot.as_quat(), grip[:, None]], axis=1)  # (5, 8) xyzw
    rows = {
        "euler": np.concatenate([pos, rot.as_euler("xyz"), grip[:, None]], axis=1),
        "axis_angle": np.concatenate([pos, rot.as_rotvec(), grip[:, None]], axis=1),
        "rot6d": np.concatenate([pos, math3d.mat_to_rot6d(rot.as_matrix()), grip[:, None]], 1),
    }
    want = parse_rows(make_adapter("rlbench", execute=5), {"actions": quat_rows})
    assert len(want) == 5
    for rotation, chunk in rows.items():
        adapter = make_adapter("rlbench", rotation=rotation, execute=5)
        assert adapter.row_width == chunk.shape[1]
        got = parse_rows(adapter, {"actions": chunk})
        for (p, q, g), (wp, wq, wg) in zip(got, want):
            assert np.array_equal(p, wp) and g == wg
            assert same_rotation(q, wq) and abs(np.linalg.norm(q) - 1) < 1e-12
        # extra columns are ignored; a row too narrow for its rotation is refused
        wide = np.concatenate([chunk, np.full((5, 2), 9.0)], axis=1)
        assert same_rotation(parse_action(adapter, {"actions": wide})[1], want[0][1])
        with pytest.raises(BadAnswer, match=rf"expected \({chunk.shape[1]},\)"):
            parse_action(adapter, {"actions": chunk[:, :-1]})
    # 7-D rows: Euler angles or rotation vectors, one action (D,) as well as a chunk
    assert rows["euler"].shape[1] == 7 and rows["axis_angle"].shape[1] == 7
    one = parse_action(make_adapter("rlbench", rotation="euler"), {"actions": rows["euler"][1]})
    assert np.array_equal(one[0], pos[1]) and same_rotation(one[1], want[1][1])
    with pytest.raises(BadAnswer, match="degenerate"):
        parse_action(make_adapter("rlbench", rotation="rot6d"),
                     {"actions": [0, 0, 0, 1, 0, 0, 2, 0, 0, 1]})
    with pytest.raises(ValueError, match="rotation must be"):
        make_adapter("rlbench", rotation="rot9d")
    with pytest.raises(ValueError, match="unknown adapter options"):
        make_adapter("rlbench", rotations="euler")
    # gripper: clipped open amount, closed amount, X-ICM's threshold
    g = [parse_action(make_adapter("rlbench", rotation="euler", **o),
                      {"actions": [[0, 0, 0, 0, 0, 0, v]]})[2]
         for o in ({}, {"gripper": "closed"}, {"gripper_threshold": 0.5})
         for v in (0.49, 0.5, 1.7)]
    assert g == [0.49, 0.5, 1.0, 0.51, 0.5, 0.0, 0.0, 1.0, 1.0]


def test_execute_and_relative_rows() -> None:
    chunk = np.array([[i, 0, 0, 0, 0, 0, 1.0] for i in range(4)])
    adapter = make_adapter("rlbench", rotation="euler", action_index=1, execute=2)
    assert [r[0][0] for r in parse_rows(adapter, {"actions": chunk})] == [1, 2]
    adapter = make_adapter("rlbench", rotation="euler", action_index=2, execute=5)
    assert [r[0][0] for r in parse_rows(adapter, {"actions": chunk})] == [2, 3]  # short chunk
    assert parse_rows(adapter, {"actions": np.zeros((0, 7))}) == []
    with pytest.raises(ValueError, match="execute"):
        make_adapter("rlbench", execute=0)
    # a delta: position added in the world frame, rotation composed on the left
    rel = make_adapter("openvla")
    assert rel.relative and rel.action_key is None and rel.rotation == "euler"
    current = Rotation.from_euler("xyz", [0.2, -0.4, 1.0])
    pose = np.concatenate([[0.3, -0.1, 0.9], current.as_quat()]).astype(np.float32)
    delta = np.array([0.01, -0.02, 0.03, 0.1, 0.05, -0.2, 0.9], np.float32)
    pos, quat, grip = apply_row(rel, parse_action(rel, delta), pose)
    assert np.allclose(pos, pose[:3].astype(np.float64) + delta[:3].astype(np.float64),
                       rtol=0, atol=1e-15)
    target = Rotation.from_euler("xyz", delta[3:6]) * Rotation.from_quat(pose[3:])
    assert same_rotation(quat, wxyz(target.as_quat()), 1e-12) and grip == 1.0
    for bad in ({"actions": delta}, "error", [[1, 2], [3]], np.zeros(6)):
        with pytest.raises(BadAnswer):
            parse_action(rel, bad)


def test_xicm_state_is_x_icms_observation_state() -> None:
    rot = Rotation.random(4, random_state=5)
    pose = np.concatenate([np.random.default_rng(0).normal(size=(4, 3)), rot.as_quat()],
                          axis=1).astype(np.float32)
    proprio = {"gripper_pose": pose, "gripper_open": np.array([1, 0, 1, 0], np.float32),
               "gripper_joint_positions": np.zeros((4, 2), np.float32)}
    state = lowdim(proprio)["xicm_state"]
    # custom_agent.py: np.concatenate((pose[:3], convert_to_euler(pose[3:])), open)
    # with utils.convert_to_euler = Rotation.from_quat(q).as_euler('xyz', degrees=False)
    for w in range(4):
        ref = np.concatenate((np.concatenate((pose[w, :3], Rotation.from_quat(
            pose[w, 3:]).as_euler("xyz", degrees=False))), proprio["gripper_open"][w:w + 1]))
        assert state[w].dtype == ref.dtype == np.float64 and state[w].shape == (7,)
        assert np.allclose(state[w], ref, rtol=0, atol=1e-12)


# ---- json_numpy ---------------------------------------------------------------------------
def test_json_wire_is_json_numpys_layout() -> None:
    raw = json.loads(json_wire.dumps({"a": np.arange(3, dtype=np.int16), "s": "text"}))
    assert raw == {"a": {"__numpy__": "AAABAAIA", "dtype": "<i2", "shape": [3]}, "s": "text"}
    image = np.random.default_rng(1).integers(0, 255, (4, 5, 3), np.uint8)
    msg = {"image": image, "x": np.float32(1.5), "chunk": [np.ones(7), np.zeros(7)],
           "f": np.asfortranarray(np.arange(6.0).reshape(2, 3))}
    back = json_wire.loads(json_wire.dumps(msg))
    assert back["image"].dtype == np.uint8 and np.array_equal(back["image"], image)
    assert back["x"] == 1.5 and back["x"].dtype == np.float32 and np.ndim(back["x"]) == 0
    assert np.array_equal(back["f"], msg["f"]) and np.asarray(back["chunk"]).shape == (2, 7)
    # as json_numpy.dumps(np.float32(1.5)) writes a scalar: shape []
    assert json.loads(json_wire.dumps(np.float32(1.5)))["shape"] == []
    with pytest.raises(TypeError):
        json_wire.dumps(np.array([object()]))


def test_http_answers_decode_like_deploy_py_writes_them() -> None:
    import asyncio

    from agnostos_mjx.remote.client import HttpTransport, ServerError, _read_response

    t = HttpTransport("http://example:9000")
    assert (t.host, t.port, t.path) == ("example", 9000, "/act")
    assert HttpTransport("https://h/v1/act?x=1").path == "/v1/act?x=1"
    action = np.arange(7, dtype=np.float32)
    assert np.array_equal(t.decode(json_wire.dumps(action).encode()), action)
    # deploy.py's double-encoded answer (JSONResponse(json_numpy.dumps(action)))
    twice = json.dumps(json_wire.dumps(action)).encode()
    assert np.array_equal(t.decode(twice), action)
    with pytest.raises(ServerError, match='"error"'):
        t.decode(b'"error"')
    with pytest.raises(ValueError):
        t.decode(b"\xc1 not json")

    async def read(raw: bytes):
        reader = asyncio.StreamReader()
        reader.feed_data(raw)
        reader.feed_eof()
        return await _read_response(reader, "POST")

    chunked = (b"HTTP/1.1 200 OK\r\nTransfer-Encoding: chunked\r\n\r\n"
               b"4\r\n[1,2\r\n3;x=y\r\n,3]\r\n0\r\n\r\n")
    assert asyncio.run(read(chunked)) == (200, {"transfer-encoding": "chunked"}, b"[1,2,3]")
    plain = b"HTTP/1.0 500 Internal Server Error\r\nContent-Length: 4\r\n\r\noops"
    assert asyncio.run(read(plain))[::2] == (500, b"oops")
    with pytest.raises(ConnectionError, match="without an answer"):
        asyncio.run(read(b""))
    with pytest.raises(asyncio.IncompleteReadError):
        asyncio.run(read(b"HTTP/1.1 200 OK\r\nContent-Length: 9\r\n\r\nabc"))


# ---- loopback servers, fake runner --------------------------------------------------------
class FakeRunner:
    """What RemotePolicy reads of an Episodes runner: proprioception and observe()."""

    def __init__(self, batch: int, size: int = 256) -> None:
        rng = np.random.default_rng(2)
        self.rot = Rotation.random(batch, random_state=3)
        self.pose = np.concatenate([rng.uniform(0, 1, (batch, 3)), self.rot.as_quat()],
                                   axis=1).astype(np.float32)
        self.open = np.ones(batch, np.float32)
        self.images = {cam: rng.integers(0, 255, (batch, size, size, 3), np.uint8)
                       for cam in ("front", "wrist", "overhead")}
        self.specs: list = []
        self.observer = SimpleNamespace(proprioception=lambda env: {
            "gripper_pose": self.pose.copy(), "gripper_open": self.open.copy(),
            "gripper_joint_positions": np.zeros((batch, 2), np.float32)})
        self.env = SimpleNamespace(done=np.zeros(batch, bool))

    def view(self, policy, instructions: list[str]):
        """What `policy` sees of these worlds now (a fresh round each call)."""
        from agnostos_mjx.policies import Round

        return Round.for_policy(policy, self, self.env, instructions)

    def observe(self, env, spec):
        self.specs.append(spec)
        return SimpleNamespace(cameras={c: SimpleNamespace(rgb=self.images[c])
                                        for c in spec.cameras})


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_xicm_preset_round_trip_and_execute() -> None:
    """X-ICM's custom_agent.py request, byte for byte in keys, shapes and dtypes; its answer
    rows [x, y, z, Euler, gripper] become key actions; execute=2 runs two rows per request."""
    pytest.importorskip("websockets")
    from agnostos_mjx.policies import make_policy
    from agnostos_mjx.remote.server import PolicyServer

    requests: list[dict] = []
    chunks = {}

    class Answer:
        def infer(self, obs: dict) -> dict:
            requests.append(obs)
            return {"actions": chunks[obs["prompt"]]}

    runner = FakeRunner(2)
    prompts = ["put the ring on the spoke", "open the box"]
    for w in range(2):  # three rows per answer; X-ICM: row = xyz, Euler (rad), gripper
        euler = Rotation.random(3, random_state=20 + w).as_euler("xyz")
        chunks[prompts[w]] = np.concatenate(
            [np.full((3, 3), w + 0.1 * np.arange(3)[:, None]), euler,
             np.array([[0.2], [0.5], [0.9]])], axis=1).astype(np.float32)
    with PolicyServer(None, session=Answer, meta={"policy": "pi0"}) as server:
        policy = make_policy("remote", url=server.url, preset="xicm", execute=2)
        assert policy.name == "remote[pi0]"
        policy.reset(runner.view(policy, prompts))
        first = policy.act(runner.view(policy, prompts))
        assert len(requests) == 2
        second = policy.act(runner.view(policy, prompts))  # the second row of each chunk: no request
        assert len(requests) == 2
        third = policy.act(runner.view(policy, prompts))
        assert len(requests) == 4
    assert runner.specs[0].cameras == ("front", "wrist", "overhead")
    assert (runner.specs[0].height, runner.specs[0].width) == (256, 256)
    for obs in requests:
        assert set(obs) == XICM_KEYS
        for key in XICM_KEYS - {"observation/state", "prompt"}:
            assert obs[key].dtype == np.uint8 and obs[key].shape == (256, 256, 3)
        assert obs["observation/state"].dtype == np.float64
        assert obs["observation/state"].shape == (7,)
        assert isinstance(obs["prompt"], str)
    by_prompt = {obs["prompt"]: obs for obs in requests[:2]}
    obs = by_prompt["open the box"]
    assert np.array_equal(obs["observation/front_image"], runner.images["front"][1])
    assert np.array_equal(obs["observation/overhead_image"], runner.images["overhead"][1])
    state = np.concatenate([runner.pose[1, :3], Rotation.from_quat(runner.pose[1, 3:])
                            .as_euler("xyz"), runner.open[1:2]])
    assert np.allclose(obs["observation/state"], state, rtol=0, atol=1e-12)
    for w in range(2):
        chunk = chunks[prompts[w]].astype(np.float64)
        for actions, row in ((first, chunk[0]), (second, chunk[1]), (third, chunk[0])):
            assert bool(actions.valid[w])
            assert np.allclose(actions.pos[w], row[:3], atol=1e-7)
            # custom_agent.py: euler_to_quaternion(row[3:6]) = from_euler("xyz", .).as_quat()
            q = wxyz(Rotation.from_euler("xyz", row[3:6]).as_quat())
            assert same_rotation(np.asarray(actions.quat[w], np.float64), q, 1e-6)
            assert actions.gripper[w] == (1.0 if row[6] >= 0.5 else 0.0)


def test_openvla_http_round_trip() -> None:
    """OpenVLA's deploy.py: POST /act {"image", "instruction", "unnorm_key"} -> a bare
    7-D delta; OFT's list of actions with execute=3 chains through the reached poses."""
    from agnostos_mjx.policies import make_policy
    from agnostos_mjx.remote.server import JsonNumpyServer

    seen: list[dict] = []
    delta = np.array([0.01, -0.02, 0.03, 0.1, 0.05, -0.2, 0.2], np.float32)

    def openvla(obs: dict):
        seen.append(obs)
        return delta  # deploy.py answers JSONResponse(action): the array itself

    runner = FakeRunner(2, size=224)
    with JsonNumpyServer(infer=openvla) as server:
        policy = make_policy("openvla", url=server.url,
                             constants=json.dumps({"unnorm_key": "agnostos"}))
        assert policy.preset == "openvla" and policy.name == "openvla"
        policy.reset(runner.view(policy, ["a", "b"]))
        actions = policy.act(runner.view(policy, ["a", "b"]))
    assert [sorted(obs) for obs in seen] == [["image", "instruction", "unnorm_key"]] * 2
    assert {obs["instruction"] for obs in seen} == {"a", "b"}
    for obs in seen:
        assert obs["image"].dtype == np.uint8 and obs["image"].shape == (224, 224, 3)
        assert obs["unnorm_key"] == "agnostos"
    for w in range(2):
        assert np.allclose(actions.pos[w], runner.pose[w, :3] + delta[:3], atol=1e-7)
        target = Rotation.from_euler("xyz", delta[3:6]) * Rotation.from_quat(runner.pose[w, 3:])
        assert same_rotation(np.asarray(actions.quat[w], np.float64), wxyz(target.as_quat()),
                             1e-6)
        assert actions.gripper[w] == 0.0  # 0.2 < 0.5: closed
    # OFT: a list of 8 actions; execute=3 runs three, each from the pose reached
    oft_chunk = [np.array([0.01 * (i + 1), 0, 0, 0, 0, 0.1, 1.0]) for i in range(8)]
    asked: list[dict] = []
    with JsonNumpyServer(infer=lambda obs: asked.append(obs) or oft_chunk) as server:
        policy = make_policy("remote", url=server.url + "/act", preset="openvla_oft",
                             execute=3)
        policy.reset(runner.view(policy, ["a", "b"]))
        start = runner.pose.copy()
        xs = []
        for _ in range(4):
            actions = policy.act(runner.view(policy, ["a", "b"]))
            xs.append(np.asarray(actions.pos[:, 0], np.float64) - runner.pose[:, 0])
            runner.pose[:, :3] = actions.pos  # the executor reached the target
            runner.pose[:, 3:] = np.asarray(actions.quat)[:, [1, 2, 3, 0]]
    assert len(asked) == 4 and sorted(asked[0]) == ["full_image", "instruction", "state",
                                                    "wrist_image"]
    assert asked[0]["state"].shape == (8,) and asked[0]["state"].dtype == np.float32
    assert np.allclose(np.array(xs)[:, 0], [0.01, 0.02, 0.03, 0.01], atol=1e-6)
    z = Rotation.from_quat(runner.pose[0, 3:]) * Rotation.from_quat(start[0, 3:]).inv()
    assert np.allclose(z.as_euler("xyz"), [0, 0, 0.4], atol=1e-5)  # four 0.1 rad turns


def test_http_client_failures_on_a_fake_runner() -> None:
    """Each failure of one world's HTTP request ends only that world, by cause."""
    from agnostos_mjx.policies import make_policy
    from agnostos_mjx.remote.server import JsonNumpyServer
    from agnostos_mjx.runtime.outcome import Outcome

    plan = ["drop", "stall", "garbage", "error", "no_actions", "http_error", None]

    def faults(obs: dict) -> str | None:
        return plan[int(obs["instruction"])]

    runner = FakeRunner(len(plan), size=8)
    answer = np.array([0, 0, 0, 0, 0, 0, 1.0])
    with JsonNumpyServer(infer=lambda obs: answer, faults=faults, stall_s=60) as server:
        policy = make_policy("openvla", url=server.url, timeout_s=2, height=8, width=8)
        prompts = [str(i) for i in range(len(plan))]
        policy.reset(runner.view(policy, prompts))
        actions = policy.act(runner.view(policy, prompts))
    assert actions.valid.tolist() == [False] * 6 + [True]
    labels = [Outcome(int(c)).label if c else None for c in actions.end_reason]
    assert labels == ["remote_error", "remote_timeout", "bad_remote_output", "remote_error",
                      "bad_remote_output", "remote_error", None]
    errors = [policy.episode_info(w).get("error", "") for w in range(len(plan))]
    assert "without an answer" in errors[0] and '"error"' in errors[3]
    assert "HTTP 500" in errors[5]
    report = policy.report()["remote"]
    assert report["requests"] == 7 and sum(report["failures"].values()) == 6
    with pytest.raises(ValueError, match="cannot reach"):
        make_policy("openvla", url=f"http://127.0.0.1:{free_port()}", connect_timeout_s=2)
    with pytest.raises(ValueError, match="http://HOST:PORT"):
        make_policy("openvla", url="ftp://x")


# ---- end to end: the evaluator, the served oracle -----------------------------------------
def _episodes(out: Path) -> list[dict]:
    records = [json.loads(line) for line in (out / "episodes.jsonl").read_text().splitlines()]
    return sorted(records, key=lambda r: (r["task"], r["seed"], r["episode"]))


def _run(out: Path, tasks: str, episodes: int, *args: str) -> int:
    return ev.main(["--tasks", tasks, "--seeds", "0", "--episodes", str(episodes),
                    "--batch", str(episodes), "--quiet", "--out", str(out), *args])


@pytest.fixture(scope="module")
def local_oracle(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("local")
    assert _run(out, "lamp_on,phone_on_base", 2, "--policy", "oracle") == 0
    return out


def _oracle_row(answer: dict) -> np.ndarray | None:
    actions = np.asarray(answer["actions"], np.float64)
    return actions[0] if len(actions) else None


@pytest.mark.slow
def test_xicm_preset_runs_the_served_oracle(tmp_path: Path, local_oracle: Path) -> None:
    """The evaluator's xicm requests (plus sim_state, for the oracle behind it) to a server
    answering X-ICM's rows [x, y, z, Euler, gripper]: the oracle's episodes."""
    pytest.importorskip("websockets")
    from agnostos_mjx.policies import make_policy
    from agnostos_mjx.remote.server import PolicyServer, Session

    oracle = make_policy("oracle")
    seen: list[dict] = []

    class XICMAnswers:
        def __init__(self) -> None:
            self.session = Session(oracle)

        def infer(self, obs: dict) -> dict:
            seen.append({k: (v.dtype, v.shape) if isinstance(v, np.ndarray) else type(v)
                         for k, v in obs.items() if k != "sim_state"})
            row = _oracle_row(self.session.infer(obs))
            if row is None:
                return {"actions": np.zeros((0, 7), np.float32)}
            euler = Rotation.from_quat(row[3:7]).as_euler("xyz")  # X-ICM's convert_to_euler
            return {"actions": np.concatenate([row[:3], euler, row[7:8]])[None]}

    keys = {"observation/front_image": "front_rgb", "observation/wrist_image": "wrist_rgb",
            "observation/overhead_image": "overhead_rgb", "observation/state": "xicm_state",
            "prompt": "instruction", "sim_state": "sim_state"}
    with PolicyServer(oracle, session=XICMAnswers) as server:
        assert _run(tmp_path / "xicm", "lamp_on,phone_on_base", 2, "--policy", "remote",
                    "--policy-url", server.url, "--policy-arg", "preset=xicm",
                    "--policy-arg", f"keys={json.dumps(keys)}", "--policy-arg",
                    "height=64", "--policy-arg", "width=64") == 0
    served, local = _episodes(tmp_path / "xicm"), _episodes(local_oracle)
    assert [{k: r[k] for k in SAME} for r in served] == [{k: r[k] for k in SAME}
                                                         for r in local]
    assert all(r["success"] for r in served)
    assert seen and all(set(s) == XICM_KEYS for s in seen)
    assert seen[0]["observation/front_image"] == (np.dtype(np.uint8), (64, 64, 3))
    assert seen[0]["observation/state"] == (np.dtype(np.float64), (7,))


@pytest.mark.slow  # test_openvla_http_round_trip checks the protocol in the default suite
def test_openvla_deltas_over_http_run_the_served_oracle(tmp_path: Path,
                                                        local_oracle: Path) -> None:
    """OpenVLA's protocol and 7-D deltas from the oracle: the oracle's episodes."""
    from agnostos_mjx.policies import make_policy
    from agnostos_mjx.remote.server import EpisodeSessions, JsonNumpyServer

    sessions = EpisodeSessions(make_policy("oracle"))

    def deltas(obs: dict):
        row = _oracle_row(sessions.infer(obs))
        if row is None:
            return np.zeros((0, 7))
        pose = np.asarray(obs["pose"], np.float64)
        turn = Rotation.from_quat(row[3:7]) * Rotation.from_quat(pose[3:]).inv()
        return np.concatenate([row[:3] - pose[:3], turn.as_euler("xyz"), row[7:8]])

    keys = {"instruction": "instruction", "sim_state": "sim_state", "pose": "gripper_pose"}
    with JsonNumpyServer(infer=deltas) as server:
        assert _run(tmp_path / "openvla", "lamp_on,phone_on_base", 2, "--policy", "openvla",
                    "--policy-arg", f"url={server.url}",
                    "--policy-arg", f"keys={json.dumps(keys)}",
                    "--policy-arg", "gripper_threshold=null") == 0
    served, local = _episodes(tmp_path / "openvla"), _episodes(local_oracle)
    assert [{k: r[k] for k in SAME} for r in served] == [{k: r[k] for k in SAME}
                                                         for r in local]
    results = json.loads((tmp_path / "openvla" / "results.json").read_text())
    assert results["policy"]["name"] == "openvla"
    assert results["remote"]["failures"] == {} and results["remote"]["requests"] > 0


def test_http_faults_end_only_their_episodes(tmp_path: Path, capfd) -> None:
    """tests/test_serve.py's fault test over HTTP: the served oracle (preset sim, from the
    server's metadata at GET /), one fault per episode."""
    from agnostos_mjx.policies import make_policy
    from agnostos_mjx.remote.server import JsonNumpyServer

    plan = {0: "drop", 1: "stall", 2: "garbage", 3: "error", 4: "no_actions",
            5: "http_error"}

    def faults(obs: dict) -> str | None:
        state = obs["sim_state"]  # episode seed = seed * 100003 + episode; seed 0 here
        return plan.get(int(state["episode_seed"])) if state["key_actions"] == 1 else None

    with JsonNumpyServer(make_policy("oracle"), faults=faults, stall_s=3600) as server:
        # warm the served oracle (scene, jitted expert) so the timeout measures the stall
        assert _run(tmp_path / "warm", "lamp_on", 1, "--policy", "remote", "--policy-url",
                    server.url) == 0
        capfd.readouterr()
        code = _run(tmp_path / "faults", "lamp_on", 8, "--policy", "remote",
                    "--policy-url", server.url, "--policy-arg", "timeout_s=5")
    out, err = capfd.readouterr()
    assert code == 0  # 6 of ~22 requests failed: not "mostly failed"
    assert "Traceback" not in out + err
    outcomes = {r["episode"]: r["outcome"] for r in _episodes(tmp_path / "faults")}
    assert outcomes == {0: "remote_error", 1: "remote_timeout", 2: "bad_remote_output",
                        3: "remote_error", 4: "bad_remote_output", 5: "remote_error",
                        6: "success", 7: "success"}
    info = {r["episode"]: r["policy_info"] for r in _episodes(tmp_path / "faults")}
    assert '"error"' in info[3]["error"] and "HTTP 500" in info[5]["error"]
    assert info[6] == {}
    results = json.loads((tmp_path / "faults" / "results.json").read_text())
    assert results["policy"]["name"] == "remote[oracle]" and results["remote"]["preset"] == "sim"
    assert "policy server" in out and "remote_timeout: 1" in out


def test_unreachable_http_server_is_a_usage_error(tmp_path: Path, capsys) -> None:
    code = ev.main(["--tasks", "lamp_on", "--policy", "remote", "--policy-url",
                    f"http://127.0.0.1:{free_port()}", "--policy-arg", "connect_timeout_s=2",
                    "--out", str(tmp_path / "x"), "--quiet"])
    assert code == 2 and "cannot reach the policy server" in capsys.readouterr().err
    code = ev.main(["--tasks", "lamp_on", "--policy", "openvla", "--out", str(tmp_path / "y"),
                    "--quiet"])
    assert code == 2 and "--policy openvla needs --policy-arg url=" in capsys.readouterr().err
