"""LeRobot's ``EnvConfig`` of type ``agnostos`` (``--env.type=agnostos``): its fields are
agnostos_mjx.gym_env.EnvOptions' (the LeRobot export's layout flags and how episodes run),
``features`` / ``features_map`` name the export's keys, and ``create_envs`` returns
``{suite: {task_id: AgnostosVectorEnv}}``.

The cameras, image size, state and rotation default to the policy's: lerobot-eval and
lerobot-train build this config before they load the policy, and build the envs from it
before the policy sees an observation, so the config reads the policy's features itself,
from ``--policy.path`` as lerobot-eval does (``EvalPipelineConfig.__post_init__``), and the
names of its state and action dimensions from its training data: lerobot-train's
``--dataset.repo_id`` / ``--dataset.root`` (a policy trained from scratch takes its inputs
from there: ``make_policy(ds_meta=...)``), else the dataset the checkpoint's
train_config.json names, when it is on this machine.  Any input the env cannot give stops
the command in one line.  That dataset's info.json goes to the envs, which log one
warning line, once, at their first reset when it records another renderer or scene
version than they render with (the export's "agnostos" record, data/look.py): the policy
will see slightly different images.  Checked against lerobot 0.6.1's src/lerobot/envs/configs.py
(EnvConfig, create_envs), configs/eval.py, configs/train.py, envs/utils.py
(preprocess_observation), scripts/lerobot_eval.py (eval_main, rollout) and
scripts/lerobot_train.py (the envs of ``--env_eval_freq``)."""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

from lerobot.configs import FeatureType, PolicyFeature, parser
from lerobot.envs.configs import EnvConfig

from agnostos_mjx.gym_env import (
    dataset_inputs,
    lerobot_features,
    make_suites,
    options_for_policy,
    resolve_tasks,
)


def policy_features() -> dict[str, tuple[int, ...]] | None:
    """Shapes of the input and output features of the policy named by ``--policy.path``
    (lerobot-eval's, or lerobot-train's to fine-tune), read as lerobot-eval reads it; None
    when the command names none."""
    path = parser.get_path_arg("policy")
    if not path:
        return None
    from lerobot.configs.policies import PreTrainedConfig

    cfg = PreTrainedConfig.from_pretrained(path, cli_overrides=parser.get_cli_overrides("policy")
                                           or [])
    return {key: tuple(ft.shape) for key, ft in {**cfg.input_features,
                                                **cfg.output_features}.items()}


def dataset_info() -> dict | None:
    """The meta/info.json of the policy's training data, as written (LeRobot's own
    metadata object drops keys it does not know, our "agnostos" record among them):
    lerobot-train's dataset (``--dataset.repo_id``, ``--dataset.root``, found as
    lerobot-train finds it), else the one the ``--policy.path`` checkpoint was trained on
    (its train_config.json) when it is on this machine (an evaluation downloads no
    dataset); None when neither."""
    repo_id = parser.parse_arg("dataset.repo_id")
    if repo_id:
        from lerobot.datasets import LeRobotDatasetMetadata

        meta = LeRobotDatasetMetadata(repo_id, root=parser.parse_arg("dataset.root"),
                                      revision=parser.parse_arg("dataset.revision"))
        return json.loads((Path(meta.root) / "meta/info.json").read_text())
    path = parser.get_path_arg("policy")
    train_config = Path(path) / "train_config.json" if path else None
    if train_config is None or not train_config.is_file():  # none, or a Hub repo id
        return None
    dataset = json.loads(train_config.read_text()).get("dataset") or {}
    root, repo_id = dataset.get("root"), dataset.get("repo_id")
    if not root and not isinstance(repo_id, str):  # none, or a list of datasets
        return None
    from lerobot.utils.constants import HF_LEROBOT_HOME

    info = Path(root or HF_LEROBOT_HOME / repo_id) / "meta/info.json"
    return json.loads(info.read_text()) if info.is_file() else None


@EnvConfig.register_subclass("agnostos")
@dataclass
class AgnostosEnvConfig(EnvConfig):
    """``task``: a task, a suite (seen, level1, level2, unseen) or a comma-separated mix.
    ``cameras`` (comma-separated), ``size``, ``state``, ``rotation``: the export's flags of
    the training data; they default to the policy's image inputs and its training data's
    state and action names (without either: all five cameras at 224 px, rlbench state,
    quat actions).  ``renderer``: auto, cpu (as the export renders) or warp.  The rest:
    agnostos_mjx.gym.env's module docstring."""

    task: str | None = "unseen"
    fps: int = 10  # the export's nominal keyframe rate
    cameras: str | None = None
    size: int | None = None
    state: str | None = None
    rotation: str | None = None
    control_mode: str = "keyaction"
    control_hz: float = 20.0  # control_mode dense: control steps per second
    dense_steps: int | None = None  # control_mode dense: the step budget
    backend: str = "native"
    variations: str = "protocol"
    protocol_seed: int = 0
    render_camera: str = "front"
    render_size: int | None = None
    autoreset_mode: str = "next_step"
    renderer: str = "auto"
    features: dict[str, PolicyFeature] = field(default_factory=dict)
    features_map: dict[str, str] = field(default_factory=dict)

    def __post_init__(self) -> None:
        policy = policy_features()
        info = dataset_info()
        data = info.get("features") if info else None
        shapes, names = dataset_inputs(data) if data is not None else ({}, {})
        if policy is None and shapes:  # a policy trained from scratch on the dataset
            policy = shapes
        try:  # a ValueError names a bad option, or the policy's inputs this env cannot give
            opts = options_for_policy(policy, names, **self.gym_kwargs)
        except ValueError as e:
            if policy is None and not names:
                raise
            # the policy came from the command line: stop it with one line, not a traceback
            # of the config parser's
            raise SystemExit(f"--env.type=agnostos: {e}") from None
        self.cameras, self.size = ",".join(opts.cameras), opts.size
        self.state, self.rotation = opts.state, opts.rotation
        resolve_tasks(self.task or "")
        # not a field: the envs' (their look warning), not part of the saved config
        self._training_data = info
        for key, (kind, shape, policy_key) in lerobot_features(opts).items():
            self.features[key] = PolicyFeature(type=FeatureType[kind], shape=shape)
            self.features_map[key] = policy_key

    @property
    def package_name(self) -> str:
        return "lerobot_env_agnostos"

    @property
    def gym_kwargs(self) -> dict:
        return {"cameras": self.cameras, "size": self.size, "state": self.state,
                "rotation": self.rotation, "control_mode": self.control_mode,
                "control_hz": self.control_hz, "dense_steps": self.dense_steps,
                "backend": self.backend, "variations": self.variations,
                "protocol_seed": self.protocol_seed, "render_camera": self.render_camera,
                "render_size": self.render_size, "autoreset_mode": self.autoreset_mode,
                "renderer": self.renderer}

    def create_envs(self, n_envs: int, use_async_envs: bool = False) -> dict:
        """One VectorEnv of `n_envs` worlds per task.  `use_async_envs` is moot: the worlds
        of a task already run as one batch in this process (native MuJoCo's threads)."""
        return make_suites(self.task or "", n_envs, getattr(self, "_training_data", None),
                           "--env.renderer", **self.gym_kwargs)
