"""The gymnasium VectorEnv behind the LeRobot plug-in (agnostos_mjx/gym/): gymnasium's
own checks where they apply to a vector env, determinism, autoreset, the LeRobot export's
keys and rows (an exported demo replays through it frame for frame), the expert's key
actions replayed on 3 seen tasks, and clear errors.  No lerobot, no torch (the real
lerobot-eval run: eval/reports/lerobot_interop/train_eval.py)."""

from __future__ import annotations

import functools
import importlib.util
import re
import sys
import tomllib
from pathlib import Path

import numpy as np
import pytest

gym = pytest.importorskip("gymnasium")

from gymnasium.utils import env_checker  # noqa: E402

from agnostos_mjx.data import lerobot_layout as layout  # noqa: E402
from agnostos_mjx.gym_env import (  # noqa: E402
    AgnostosVectorEnv,
    EnvOptions,
    dataset_inputs,
    lerobot_features,
    make_suites,
    options_for_policy,
    resolve_tasks,
)
from agnostos_mjx.runtime.outcome import Outcome  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
PLUGIN = REPO / "lerobot_env_agnostos"
SMALL = dict(cameras=("front",), size=32)


def _env(task: str, n: int = 2, **options) -> AgnostosVectorEnv:
    """One env per task, size and options for the module (building a scene costs seconds)."""
    return _cached(task, n, EnvOptions(**{**SMALL, **options}))


@functools.cache
def _cached(task: str, n: int, options: EnvOptions) -> AgnostosVectorEnv:
    return AgnostosVectorEnv(task, n, options)


def _replay(env: AgnostosVectorEnv, seed) -> tuple[np.ndarray, np.ndarray, list]:
    """Reset, then step every world with its expert's rows until all episodes ended;
    returns (success, steps taken, the step results)."""
    env.reset(seed=seed)
    rows, valid = env.expert_actions()
    ended, success = np.zeros(env.num_envs, bool), np.zeros(env.num_envs, bool)
    steps = np.zeros(env.num_envs, int)
    results = []
    for k in range(rows.shape[1]):
        assert valid[~ended, k].all(), "the expert ran out of actions before the episode ended"
        out = env.step(rows[:, k])
        results.append(out)
        _, reward, term, trunc, info = out
        now = (term | trunc) & ~ended
        won = info["final_info"]["is_success"] if "final_info" in info else info["is_success"]
        success |= now & won  # as lerobot-eval's rollout reads it
        np.testing.assert_array_equal(reward, ((term | trunc) & won).astype(float))
        steps[now] = k + 1
        ended |= now
        if ended.all():
            break
    return success, steps, results


@pytest.mark.parametrize("task,rotation", [  # the default suite replays an exported demo
    pytest.param(t, r, marks=pytest.mark.slow) for t, r in (("push_buttons", "quat"),
                                                            ("turn_tap", "euler"),
                                                            ("open_drawer", "rot6d"))])
def test_expert_rows_replay_to_success(task, rotation) -> None:
    """The expert's key actions, as the export writes them (its rotation), executed one
    per step: every world succeeds, within the 25-step budget, terminated not truncated."""
    env = _env(task, rotation=rotation)
    success, steps, results = _replay(env, seed=0)
    assert success.all() and (steps <= env._max_episode_steps).all()
    assert env.call("_max_episode_steps") == (25, 25)
    last = results[-1]
    assert not last[3].any()  # truncated


def test_gymnasium_checks_and_determinism() -> None:
    """gymnasium's env checks that apply to a vector env, and same seed -> same data."""
    env = _env("lamp_on", 1)
    assert env.observation_space == gym.vector.utils.batch_space(env.single_observation_space, 1)
    assert env.action_space == gym.vector.utils.batch_space(env.single_action_space, 1)
    env_checker.check_space_limit(env.single_observation_space, "observation")
    env_checker.check_space_limit(env.single_action_space, "action")
    env_checker.check_reset_seed_determinism(env)
    env_checker.check_reset_options(env)
    env_checker.check_returned_data_not_reused(env)
    # the checkers skip the equivalences for envs without a spec: assert them here
    a, _ = env.reset(seed=5)
    b, _ = env.reset(seed=5)
    c, _ = env.reset(seed=6)
    assert env_checker.data_equivalence(a, b, exact=True)
    assert not env_checker.data_equivalence(a, c)
    # random actions (mostly unreachable targets): valid data, the same for the same seed
    env.action_space.seed(3)
    actions = [env.action_space.sample() for _ in range(2)]
    runs = []
    for _ in range(2):
        env.reset(seed=7)
        runs.append([env.step(act) for act in actions])
    assert env_checker.data_equivalence(runs[0], runs[1], exact=True)
    for obs, reward, term, trunc, info in runs[0]:
        assert obs in env.observation_space
        assert reward.dtype == np.float64 and term.dtype == trunc.dtype == bool
        assert info["is_success"].shape == (1,) and info["is_success"].dtype == bool


def test_reset_follows_the_protocol() -> None:
    """Seed g of a world is the protocol's episode g; reset() goes on to the next ones."""
    from agnostos_mjx.evaluation.protocol import episode_keys, episode_variations

    env = _env("push_buttons")
    obs, info = env.reset(seed=[4, 9])
    np.testing.assert_array_equal(info["episode"], [4, 9])
    keys = episode_keys(np.array([0, 0]), np.array([4, 9]))
    want = episode_variations(keys, env._task.num_variations, "seen", "protocol")
    np.testing.assert_array_equal(env._state.variation, want)
    assert env.call("task_description") == tuple(env._task.descriptions(int(v))[0]
                                                 for v in want)
    _, info = env.reset()
    np.testing.assert_array_equal(info["episode"], [6, 11])
    _, info = env.reset(seed=3)  # an int seeds world i with 3 + i, as gymnasium does
    np.testing.assert_array_equal(info["episode"], [3, 4])
    frames = env.render()
    assert len(frames) == 2 and frames[0].shape == (32, 32, 3) and frames[0].dtype == np.uint8
    np.testing.assert_array_equal(frames[1], env._last_obs["pixels"]["front"][1])


@pytest.mark.parametrize("mode", ["next_step", pytest.param("same_step", marks=pytest.mark.slow)])
def test_autoreset(mode) -> None:
    """A world whose episode ended starts the next one of its seed sequence (g + n): on
    the next step, its action ignored (next_step), or at once with the ended episode's
    observation and info in final_obs / final_info (same_step)."""
    env = _env("push_buttons", autoreset_mode=mode)
    assert env.metadata["autoreset_mode"].name == mode.upper()
    _, steps, results = _replay(env, seed=0)
    first = int(steps.min())  # push_buttons' variations take different numbers of actions
    w = int(np.argmin(steps))
    assert steps.max() > first
    obs, _, term, _, info = results[first - 1]
    ended_info = info["final_info"] if mode == "same_step" else info
    assert term[w] and ended_info["episode"][w] == w and ended_info["key_actions"][w] == first
    assert ended_info["outcome"][w] == Outcome.SUCCESS
    fresh_obs, _ = env.reset(seed=[w + 2, w + 2])  # the episode the world went on to
    if mode == "same_step":
        assert info["final_info"]["is_success"][w] and info["_final_obs"][w]
        assert not info["is_success"][w] and info["key_actions"][w] == 0
        assert info["episode"][w] == w + 2
        assert info["final_obs"][w]["agent_pos"].shape == (8,)
        np.testing.assert_array_equal(obs["agent_pos"][w], fresh_obs["agent_pos"][0])
    else:
        assert info["is_success"][w]
        obs, reward, term, trunc, info = results[first]
        assert not (term[w] or trunc[w] or info["is_success"][w]) and reward[w] == 0
        assert info["episode"][w] == w + 2 and info["key_actions"][w] == 0
        assert info["outcome"][w] == Outcome.RUNNING  # the new episode runs
        np.testing.assert_array_equal(obs["pixels"]["front"][w], fresh_obs["pixels"]["front"][0])


@pytest.mark.parametrize("state,rotation", [
    ("rlbench", "quat"), pytest.param("xicm", "euler", marks=pytest.mark.slow)])
def test_an_exported_demo_replays_frame_for_frame(tmp_path, state, rotation) -> None:
    """The export (32 px, front camera): the env started on the demo's scene observes the
    demo's first frame (keys, image, state), and stepping the dataset's action rows
    reproduces every later frame until the task succeeds."""
    from agnostos_mjx.data import export as ex
    from agnostos_mjx.data.generate import demo_keys
    from agnostos_mjx.data.lerobot import read_lerobot

    out = tmp_path / "ds"
    assert ex.main(["--format", "lerobot", "--out", str(out), "--tasks", "push_buttons",
                    "--demos", "1", "--cameras", "front", "--size", "32", "--batch", "1",
                    "--state", state, "--rotation", rotation, "--quiet"]) == 0
    data = read_lerobot(out)
    frames = data["frames"]
    feats = {k: v for k, v in data["info"]["features"].items()
             if k.startswith("observation") or k == "action"}
    opts = EnvOptions(state=state, rotation=rotation, **SMALL)
    mapped = {policy: shape for _, shape, policy in lerobot_features(opts).values()}
    assert mapped == {k: tuple(v["shape"]) for k, v in feats.items()}
    env = _env("push_buttons", 1, state=state, rotation=rotation)
    task = env._task
    obs, _ = env.reset(options={"episode_keys": np.asarray(demo_keys(0, task.name, [0], [0])),
                                "variations": [0 % task.num_variations]})
    assert env.task_description[0] == frames[0]["task"]
    # rlbench's state is the observed pose as it is: equal bits.  xicm's Euler angles come
    # from numpy's vectorised trigonometry, whose last bit can depend on how many rows one
    # call converts (the export converts an episode at once, the env a batch of worlds).
    tol = 0.0 if state == "rlbench" else 1e-9
    steps = 0
    for frame in frames:
        np.testing.assert_array_equal(obs["pixels"]["front"][0],
                                      frame["observation.images.front"])
        np.testing.assert_allclose(obs["agent_pos"][0], frame["observation.state"], rtol=0,
                                   atol=tol)
        obs, _, term, trunc, info = env.step(frame["action"][None])
        steps += 1
        if term[0] or trunc[0]:
            break
    assert info["is_success"][0] and steps == len(frames) - 1


def test_suites_features_and_plugin_package() -> None:
    """--env.task names, the LeRobot feature map (the export's keys), and the plug-in's
    distribution: Name lerobot_env_agnostos, importable without lerobot."""
    suites = resolve_tasks("level1")
    assert list(suites) == ["level1"] and len(suites["level1"]) == 13
    mixed = resolve_tasks("lamp_on, push_buttons,seen")
    assert mixed["seen"][:2] == ["push_buttons", "open_drawer"] and len(mixed["seen"]) == 18
    assert sum(map(len, resolve_tasks("unseen").values())) == 23
    envs = make_suites("lamp_on,turn_tap", 3, **SMALL)
    assert {s: {i: e.task for i, e in d.items()} for s, d in envs.items()} == {
        "level1": {0: "lamp_on"}, "seen": {0: "turn_tap"}}
    assert envs["seen"][0].num_envs == 3 and envs["seen"][0]._episodes is None  # lazy
    opts = EnvOptions(cameras="front,wrist", size=64, state="libero", rotation="axis_angle")
    feats = lerobot_features(opts)
    export = layout.features(opts.cameras, 64, 64, "libero", "axis_angle")
    assert {p: s for _, s, p in feats.values()} == {
        k: tuple(v["shape"]) for k, v in export.items() if k not in layout.DEFAULT_FEATURES}
    assert feats["pixels/wrist"][2] == "observation.images.wrist"
    meta = tomllib.loads((PLUGIN / "pyproject.toml").read_text())["project"]
    assert meta["name"] == "lerobot_env_agnostos"
    assert {"agnostos-mjx", "gymnasium>=1.1"} <= set(meta["dependencies"])
    if importlib.util.find_spec("lerobot") is None:
        sys.path.insert(0, str(PLUGIN))
        try:
            import lerobot_env_agnostos
        finally:
            sys.path.remove(str(PLUGIN))
        assert lerobot_env_agnostos.AgnostosVectorEnv is AgnostosVectorEnv
        assert not hasattr(lerobot_env_agnostos, "AgnostosEnvConfig")


# A policy trained on the export's front + wrist cameras at 64 px (LeRobot's feature shapes).
ACT_64 = {"observation.images.front": (3, 64, 64), "observation.images.wrist": (3, 64, 64),
          "observation.state": (8,), "action": (8,)}


def test_options_take_the_policys_cameras_and_size() -> None:
    """Cameras and size left unset come from the policy's image inputs, so the env gives
    exactly the keys and shapes it was trained on; without a policy, the export's
    defaults; given options that cover the policy's inputs stand."""
    opts = options_for_policy(ACT_64)
    assert (opts.cameras, opts.size) == (("front", "wrist"), 64)
    given = {policy: (shape[2], *shape[:2]) if len(shape) == 3 else shape
             for _, shape, policy in lerobot_features(opts).values()}
    assert given == ACT_64  # HWC images as preprocess_observation turns them into CHW
    opts = options_for_policy(None)
    assert (len(opts.cameras), opts.size) == (5, 224)
    opts = options_for_policy(ACT_64, cameras="wrist,front,overhead", size=64)
    assert (opts.cameras, opts.size) == (("wrist", "front", "overhead"), 64)
    euler = {"observation.images.wrist": (3, 32, 32), "observation.state": (7,),
             "action": (7,)}
    opts = options_for_policy(euler, state="xicm", rotation="euler", cameras=None, size=None)
    assert (opts.cameras, opts.size, opts.state_dim, opts.action_dim) == (("wrist",), 32, 7, 7)


@pytest.mark.parametrize("policy,options,named", [
    (ACT_64, dict(size=224), [r"observation.images.front \(3, 64, 64\)",
                              r"observation.images.wrist \(3, 64, 64\)", "leave size unset"]),
    (ACT_64, dict(cameras="front"), [r"observation.images.wrist \(3, 64, 64\)",
                                     "leave cameras unset"]),
    (ACT_64, dict(rotation="euler"), [r"action \(8,\)", "rotation euler"]),
    (ACT_64, dict(state="xicm"), [r"observation.state \(8,\)", "state xicm"]),
    ({**ACT_64, "observation.images.top": (3, 64, 64)}, {}, ["observation.images.top",
                                                             "no such camera"]),
    ({**ACT_64, "observation.environment_state": (4,)}, {},
     [r"observation.environment_state \(4,\)"]),
    ({"observation.images.front": (3, 64, 48)}, {}, [r"\(3, 64, 48\)", "RGB squares"]),
    ({"observation.images.front": (3, 64, 64), "observation.images.wrist": (3, 32, 32)}, {},
     [r"observation.images.wrist \(3, 32, 32\)"]),
])
def test_a_policy_the_env_cannot_feed_is_a_one_line_error(policy, options, named) -> None:
    """Never a silent 0%: each input the env cannot give is named, in one line."""
    with pytest.raises(ValueError, match="the policy wants what this env does not give") as e:
        options_for_policy(policy, **options)
    message = str(e.value)
    assert "\n" not in message
    for pattern in named:
        assert re.search(pattern, message), (pattern, message)


def test_the_training_datas_names_set_the_layouts() -> None:
    """The export's info.json as a policy trained on it sees it (images channel-first, as
    LeRobot's dataset_to_policy_features): its shapes set cameras and size, its state and
    action names the state and rotation layouts, which lengths alone cannot tell apart."""
    feats = layout.features(("front", "wrist"), 64, 64, "libero", "axis_angle",
                            video_info={"video.codec": "h264"})
    shapes, names = dataset_inputs(feats)
    assert shapes == {"observation.images.front": (3, 64, 64),
                      "observation.images.wrist": (3, 64, 64), "observation.state": (8,),
                      "action": (7,)}
    assert names == {"observation.state": layout.STATE_NAMES["libero"],
                     "action": layout.action_names("axis_angle")}
    opts = options_for_policy(shapes, names)
    assert (opts.cameras, opts.size, opts.state, opts.rotation) == (
        ("front", "wrist"), 64, "libero", "axis_angle")
    assert options_for_policy(shapes, names, state="libero").state == "libero"


@pytest.mark.parametrize("data,options,named", [
    (("rlbench", "quat"), dict(state="libero"),
     ["observation.state named x,y,z,qx,qy,qz,qw,gripper_open (state rlbench)",
      "for state libero", "leave state unset"]),
    (("xicm", "euler"), dict(rotation="axis_angle"),
     ["action named x,y,z,rx,ry,rz,gripper (rotation euler)", "for rotation axis_angle",
      "leave rotation unset"]),
    (("libero", "quat"), dict(state="rlbench", size=64),
     ["observation.state named x,y,z,ax,ay,az,finger_joint1,finger_joint2 (state libero)",
      "leave size and state unset"]),
])
def test_another_layout_of_the_same_length_is_a_one_line_error(data, options, named) -> None:
    """--env.state=libero for an rlbench-state policy (both 8 long) would run silently."""
    shapes, names = dataset_inputs(layout.features(("front",), 64, 64, *data))
    with pytest.raises(ValueError, match="the policy wants what this env does not give") as e:
        options_for_policy(shapes, names, **options)
    assert "\n" not in str(e.value)
    for part in named:
        assert part in str(e.value), (part, str(e.value))
    names = {**names, "observation.state": ("joint1", "joint2", "joint3", "joint4", "joint5",
                                            "joint6", "joint7", "gripper")}
    with pytest.raises(ValueError, match=r"observation.state named joint1,.*,gripper \(no "
                                         r"layout of ours\)"):
        options_for_policy(shapes, names)


# Just what lerobot_env_agnostos.configuration_agnostos imports from lerobot, so the
# plug-in's config runs here without lerobot or torch; policy configs as config.json,
# datasets as meta/info.json.
FAKE_LEROBOT = {
    "lerobot/__init__.py": "",
    "lerobot/envs/__init__.py": "",
    "lerobot/configs/__init__.py": """
import enum
from dataclasses import dataclass

FeatureType = enum.Enum("FeatureType", "STATE VISUAL ENV ACTION")

@dataclass
class PolicyFeature:
    type: FeatureType
    shape: tuple
""",
    "lerobot/configs/parser.py": """
import sys

def parse_arg(name):
    opt = f"--{name}="
    return next((a[len(opt):] for a in sys.argv[1:] if a.startswith(opt)), None)

def get_path_arg(field):
    return parse_arg(f"{field}.path")

def get_cli_overrides(field):
    return []
""",
    "lerobot/configs/policies.py": """
import json
from pathlib import Path
from types import SimpleNamespace

class PreTrainedConfig:
    @classmethod
    def from_pretrained(cls, path, cli_overrides=()):
        cfg = json.loads((Path(path) / "config.json").read_text())
        feats = lambda d: {k: SimpleNamespace(shape=v["shape"]) for k, v in d.items()}
        return SimpleNamespace(input_features=feats(cfg["input_features"]),
                               output_features=feats(cfg["output_features"]))
""",
    "lerobot/envs/configs.py": """
from dataclasses import dataclass, field

@dataclass
class EnvConfig:
    task: str | None = None
    fps: int = 30
    features: dict = field(default_factory=dict)
    features_map: dict = field(default_factory=dict)

    @classmethod
    def register_subclass(cls, name):
        return lambda sub: sub
""",
    "lerobot/utils/__init__.py": "",
    "lerobot/utils/constants.py": """
import os
from pathlib import Path

HF_LEROBOT_HOME = Path(os.environ["HF_LEROBOT_HOME"])
""",
    "lerobot/datasets/__init__.py": """
import json
from pathlib import Path

from lerobot.utils.constants import HF_LEROBOT_HOME

class LeRobotDatasetMetadata:
    def __init__(self, repo_id, root=None, revision=None):
        self.root = Path(root) if root else HF_LEROBOT_HOME / repo_id
        self.features = json.loads((self.root / "meta/info.json").read_text())["features"]
""",
}
CONFIG_RUN = """
import json, sys
from lerobot_env_agnostos.configuration_agnostos import AgnostosEnvConfig
cfg = AgnostosEnvConfig(task="lamp_on", **json.loads(sys.argv[1]))
if "--reset" in sys.argv:  # the envs' first reset (where a look warning is logged)
    for env in cfg.create_envs(1)["level1"].values():
        env.reset(seed=0)
        env.close()
print(json.dumps({"cameras": cfg.cameras, "size": cfg.size, "state": cfg.state,
                  "rotation": cfg.rotation,
                  "features": {k: list(f.shape) for k, f in cfg.features.items()}}))
"""


@pytest.fixture
def plugin_config(tmp_path):
    """Runs the plug-in's EnvConfig(task="lamp_on", **options) in a process whose command
    line is `argv`, lerobot's side faked (FAKE_LEROBOT; HF_LEROBOT_HOME = tmp_path/home)."""
    import json
    import os
    import subprocess

    fake = tmp_path / "fake"
    for name, text in FAKE_LEROBOT.items():
        (fake / name).parent.mkdir(parents=True, exist_ok=True)
        (fake / name).write_text(text)
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(fake), str(PLUGIN)]),
           "HF_LEROBOT_HOME": str(tmp_path / "home")}

    def config(options: dict, *argv: str) -> subprocess.CompletedProcess:
        return subprocess.run([sys.executable, "-c", CONFIG_RUN, json.dumps(options), *argv],
                              capture_output=True, text=True, env=env, timeout=300)

    return config


def _policy_dir(path: Path, features: dict, dataset: dict | None = None) -> Path:
    """A checkpoint's pretrained_model/ as lerobot writes it: config.json (the feature
    shapes) and, from lerobot-train, train_config.json (which names its dataset)."""
    import json

    path.mkdir(parents=True)
    shapes = lambda keys: {k: {"shape": list(features[k])} for k in keys}  # noqa: E731
    (path / "config.json").write_text(json.dumps({
        "input_features": shapes([k for k in features if k != "action"]),
        "output_features": shapes(["action"])}))
    if dataset is not None:
        (path / "train_config.json").write_text(json.dumps({"dataset": dataset}))
    return path


def _dataset(root: Path, cameras, size: int, state: str, rotation: str,
             look: dict | None = None) -> Path:
    """A dataset's meta/info.json as the export writes it (data/lerobot.py: features;
    `look`: its "agnostos" record, data/look.py)."""
    import json

    (root / "meta").mkdir(parents=True)
    feats = layout.features(cameras, size, size, state, rotation)
    (root / "meta/info.json").write_text(json.dumps({"codebase_version": "v3.0",
                                                    "features": feats,
                                                    **({"agnostos": look} if look else {})}))
    return root


def _one_line_stop(run, *parts: str) -> None:
    assert run.returncode == 1 and run.stdout == "", run.stderr[-3000:]
    assert run.stderr.startswith("--env.type=agnostos: the policy wants what this env does "
                                 "not give: ") and run.stderr.count("\n") == 1, run.stderr
    for part in parts:
        assert part in run.stderr, (part, run.stderr)


def test_plugin_config_takes_the_policy_of_the_command_line(plugin_config, tmp_path) -> None:
    """The plug-in's EnvConfig reads the policy that ``--policy.path`` names, as
    lerobot-eval does, and builds its cameras, size and features from it, or stops with
    the one-line error."""
    import json

    policy = _policy_dir(tmp_path / "pretrained_model", ACT_64)
    eval_argv = ("--env.type=agnostos", f"--policy.path={policy}", "--policy.device=cpu")
    run = plugin_config({}, *eval_argv)
    assert run.returncode == 0, run.stderr[-3000:]
    got = json.loads(run.stdout)
    assert (got["cameras"], got["size"]) == ("front,wrist", 64)
    assert got["features"] == {"action": [8], "agent_pos": [8], "pixels/front": [64, 64, 3],
                               "pixels/wrist": [64, 64, 3]}
    # the policy's inputs not given: the command stops with one line that names them
    _one_line_stop(plugin_config({"size": 224}, *eval_argv),
                   "not give: observation.images.front (3, 64, 64); ", "leave size unset")
    run = plugin_config({})  # no policy on the command line: the export's defaults
    assert run.returncode == 0, run.stderr[-3000:]
    got = json.loads(run.stdout)
    assert (got["cameras"].count(","), got["size"], got["state"], got["rotation"]) == (
        4, 224, "rlbench", "quat")


RLBENCH_STATE = "observation.state named x,y,z,qx,qy,qz,qw,gripper_open (state rlbench)"


def test_plugin_config_takes_the_training_datas_inputs(plugin_config, tmp_path) -> None:
    """lerobot-train's evaluation (``--env_eval_freq``) of a policy trained from scratch:
    no --policy.path, but the dataset's info.json holds its inputs, shapes and layouts;
    the env takes them, or stops in one line on any other given; lerobot-eval finds the
    dataset through the checkpoint's train_config.json."""
    import json

    data = _dataset(tmp_path / "agnostos_seen", ("front", "wrist"), 64, "rlbench", "quat")
    train = ("--env.type=agnostos", "--env_eval_freq=100", "--policy.type=act",
             "--dataset.repo_id=local/agnostos_seen", f"--dataset.root={data}")
    run = plugin_config({}, *train)
    assert run.returncode == 0, run.stderr[-3000:]
    got = json.loads(run.stdout)
    assert (got["cameras"], got["size"], got["state"], got["rotation"]) == (
        "front,wrist", 64, "rlbench", "quat")
    assert got["features"]["pixels/wrist"] == [64, 64, 3]
    _one_line_stop(plugin_config({"size": 224}, *train),
                   "observation.images.front (3, 64, 64)", "leave size unset")
    # the same length, another layout: only the names tell
    _one_line_stop(plugin_config({"state": "libero"}, *train), RLBENCH_STATE,
                   "for state libero", "leave state unset")
    # a dataset under $HF_LEROBOT_HOME in other layouts sets them all
    _dataset(tmp_path / "home/local/xicm_seen", ("wrist",), 32, "xicm", "euler")
    run = plugin_config({}, "--env.type=agnostos", "--dataset.repo_id=local/xicm_seen")
    assert run.returncode == 0, run.stderr[-3000:]
    got = json.loads(run.stdout)
    assert (got["cameras"], got["size"], got["state"], got["rotation"]) == (
        "wrist", 32, "xicm", "euler")
    assert got["features"]["agent_pos"] == [7] and got["features"]["action"] == [7]
    # lerobot-eval: the checkpoint's train_config.json names the dataset it was trained on
    policy = _policy_dir(tmp_path / "act", ACT_64, {"repo_id": "local/agnostos_seen",
                                                    "root": str(data)})
    _one_line_stop(plugin_config({"state": "libero"}, "--env.type=agnostos",
                                 f"--policy.path={policy}"), RLBENCH_STATE)
    # ... not on this machine: the lengths are all there is to check
    policy = _policy_dir(tmp_path / "elsewhere", ACT_64, {"repo_id": "someone/else",
                                                          "root": None})
    run = plugin_config({"state": "libero"}, "--env.type=agnostos", f"--policy.path={policy}")
    assert run.returncode == 0 and json.loads(run.stdout)["state"] == "libero", run.stderr


def test_plugin_envs_warn_once_on_another_look(plugin_config, tmp_path) -> None:
    """Training data rendered otherwise than the env renders: the plug-in's envs log one
    warning line at their first reset, naming the flag that renders as the data did."""
    from agnostos_mjx.data.look import look_record

    data = _dataset(tmp_path / "warp_seen", ("front",), 32, "rlbench", "quat",
                    look={**look_record("cpu"), "renderer": "warp"})
    run = plugin_config({"renderer": "cpu"}, "--env.type=agnostos",
                        "--dataset.repo_id=local/warp_seen", f"--dataset.root={data}", "--reset")
    assert run.returncode == 0, run.stderr[-3000:]
    lines = [x for x in run.stderr.splitlines() if "training data was rendered" in x]
    assert len(lines) == 1, run.stderr
    assert "renderer warp (here cpu)" in lines[0] and lines[0].endswith(
        "; --env.renderer=warp renders as the data was"), lines[0]


def test_env_warns_once_on_another_look(caplog) -> None:
    """The env's first reset compares the training data's look with its own, once per
    process and message; data rendered as the env renders, or with no record: silence."""
    import logging

    from agnostos_mjx.data.look import look_record

    look = look_record("cpu")
    cases = {"same": {"agnostos": look}, "none": {"features": {}},
             "other": {"agnostos": {**look, "scene_version": "0123456789ab"}}}
    with caplog.at_level(logging.WARNING, logger="agnostos_mjx.gym_env"):
        for name in ("same", "none", "other", "other"):
            env = AgnostosVectorEnv("lamp_on", 1, EnvOptions(**SMALL, renderer="cpu"),
                                    training_data=cases[name])
            env.reset(seed=0)
            env.reset(seed=1)
            env.close()
    texts = [r.getMessage() for r in caplog.records if r.name == "agnostos_mjx.gym_env"]
    assert len(texts) == 1 and "scene version 0123456789ab" in texts[0], texts
    assert "renderer=" not in texts[0]  # the renderers agree


def test_observed_images_are_the_callers_to_change(monkeypatch) -> None:
    """The GPU route's images come back as read-only JAX host buffers: the env hands out
    writable arrays (torch.from_numpy in lerobot-eval warned on each), copying only those."""
    env = AgnostosVectorEnv("lamp_on", 1, EnvOptions(**SMALL, renderer="cpu"))
    env.reset(seed=0)
    observe = env.runner.observe

    def read_only(state, spec):
        obs = observe(state, spec)
        for cam in obs.cameras.values():
            cam.rgb.setflags(write=False)
        return obs

    monkeypatch.setattr(env.runner, "observe", read_only)
    obs, *_ = env.step(np.asarray(env._last_obs["agent_pos"])[:, :8])
    assert all(img.flags.writeable for img in obs["pixels"].values())
    env.close()


@pytest.mark.parametrize("hz,fps", [(20.0, 20), (10, 10), (7.5, "15/2")])
def test_dense_render_fps_is_a_rate_pyav_takes(tmp_path, hz, fps) -> None:
    """lerobot-eval writes its episode videos with ``metadata["render_fps"]`` as PyAV's
    stream rate, which takes an int or a Fraction but no float: a dense env's 20.0 failed
    every video (lerobot 0.6.1, io_utils.write_video)."""
    from fractions import Fraction

    env = AgnostosVectorEnv("lamp_on", 1, EnvOptions(**SMALL, control_mode="dense",
                                                     control_hz=hz))
    rate = env.metadata["render_fps"]
    assert rate == Fraction(fps) and not isinstance(rate, float)
    av = pytest.importorskip("av")
    with av.open(str(tmp_path / "v.mp4"), "w") as container:
        stream = container.add_stream("mpeg4", rate=rate)
        assert stream.average_rate == Fraction(fps)


@pytest.mark.parametrize("call,match", [
    (lambda: EnvOptions(renderer="gl"), "unknown renderer"),
    (lambda: AgnostosVectorEnv("no_such_task", 1), "unknown task 'no_such_task'"),
    (lambda: resolve_tasks("level3"), "unknown task or suite 'level3'.*level1"),
    (lambda: make_suites("", 1), "must name a task or a suite"),
    (lambda: AgnostosVectorEnv("lamp_on", 0), "num_envs"),
    (lambda: EnvOptions(control_mode="dense", control_hz=0), "control_hz must be a positive rate"),
    (lambda: EnvOptions(control_mode="dense", dense_steps=0), "dense_steps must be"),
    (lambda: EnvOptions(control_mode="joint"), "unknown control_mode"),
    (lambda: EnvOptions(cameras="front,top"), "cameras must be"),
    (lambda: EnvOptions(rotation="matrix"), "unknown rotation"),
    (lambda: EnvOptions(state="joints"), "unknown state layout"),
    (lambda: EnvOptions(autoreset_mode="never"), "unknown autoreset_mode"),
    (lambda: EnvOptions(size=0), "size must be"),
    (lambda: AgnostosVectorEnv("lamp_on", 1, variations="7"), "variations 7"),
    (lambda: EnvOptions(variations="some"), "variations must be one of protocol, all"),
])
def test_bad_options_are_clear_errors(call, match) -> None:
    with pytest.raises(ValueError, match=match):
        call()


def test_bad_calls_are_clear_errors() -> None:
    env = AgnostosVectorEnv("lamp_on", 2, **SMALL)
    with pytest.raises(RuntimeError, match="reset"):
        env.step(np.zeros((2, 8)))
    with pytest.raises(ValueError, match="seed: one integer or 2"):
        env.reset(seed=[1, 2, 3])
    with pytest.raises(ValueError, match="unknown reset options"):
        env.reset(options={"scene": 1})
    env.reset(seed=0)
    with pytest.raises(ValueError, match=r"actions: shape \(2, 8\)"):
        env.step(np.zeros((2, 7)))
    # a row that is no key action ends that world as no_action; the other goes on
    rows, _ = env.expert_actions()
    bad = rows[:, 0].copy()
    bad[0, :] = np.nan
    _, _, term, _, info = env.step(bad)
    assert term[0] and info["outcome"][0] == Outcome.NO_ACTION and not term[1]
    env.close()


def test_real_lerobot_rollout_through_the_plugin(tmp_path) -> None:
    """Opt-in, with AGNOSTOS_LEROBOT_BIN = bin/ of a venv with lerobot >= 0.6, agnostos-mjx
    and the plug-in installed: LeRobot discovers the plug-in, ``make_env`` builds its
    envs and LeRobot's own ``rollout()`` counts every expert-replay episode of 3 seen tasks
    a success in both autoreset modes (eval/reports/lerobot_interop/train_eval.py's step 4;
    that script also runs lerobot-train and lerobot-eval)."""
    import json
    import os
    import subprocess

    bin_ = os.environ.get("AGNOSTOS_LEROBOT_BIN")
    if not bin_:
        pytest.skip("set AGNOSTOS_LEROBOT_BIN to bin/ of a venv with lerobot >= 0.6 and the "
                    "plug-in")
    sys.path.insert(0, str(REPO / "eval/reports/lerobot_interop"))
    try:
        import train_eval
    finally:
        sys.path.remove(str(REPO / "eval/reports/lerobot_interop"))
    side = tmp_path / "side.py"
    side.write_text(f"TASKS = {train_eval.REPLAY_TASKS!r}\n" + train_eval.SIDE)
    env = {**os.environ, "HF_HUB_OFFLINE": "1", "HF_HOME": str(tmp_path / "hf")}
    subprocess.run([str(Path(bin_) / "python"), str(side), str(tmp_path / "out.json")],
                   check=True, env=env, timeout=900, capture_output=True)
    out = json.loads((tmp_path / "out.json").read_text())
    assert out["known_env_types_has_agnostos"]
    assert len(out["replay"]) == 6 and all(all(r["successes"]) for r in out["replay"])


@pytest.mark.slow
def test_dense_rows_of_the_dense_export_replay_to_success() -> None:
    """control_mode dense: one step = one 50 ms control period; the dense export's action
    rows of each world's expert demo (the dense-replay policy's, in the export's Euler
    layout) replayed one per step succeed within the dense budget."""
    from agnostos_mjx.policies import Round
    from agnostos_mjx.policies.dense_replay import DenseReplayPolicy

    env = _env("turn_tap", 2, control_mode="dense", rotation="euler")
    assert env.call("_max_episode_steps") == (1000, 1000)
    assert env.metadata["render_fps"] == 20 and isinstance(env.metadata["render_fps"], int)
    env.reset(seed=0)
    replay = DenseReplayPolicy()
    replay.reset(Round.for_policy(replay, env.runner, env._state, ["", ""]))
    n = replay.gripper.shape[1]
    ended, success = np.zeros(2, bool), np.zeros(2, bool)
    for k in range(n + 20):
        rows = layout.action_vector("euler", replay.pose[:, min(k, n - 1)],
                                    replay.gripper[:, min(k, n - 1)])
        _, _, term, trunc, info = env.step(rows)
        success |= (term | trunc) & ~ended & info["is_success"]
        ended |= term | trunc
        if ended.all():
            break
    assert success.all() and info["key_actions"].max() <= n
