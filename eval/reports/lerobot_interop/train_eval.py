"""Opt-in: LeRobot trains on our export and evaluates on our worlds through the plug-in.

In a Python 3.12 venv with ``lerobot[dataset,training]`` 0.6.x from the package index,
agnostos-mjx and the ``lerobot_env_agnostos`` plug-in installed (``pip install -e . -e
./lerobot_env_agnostos``), all under ``HF_HUB_OFFLINE=1`` with ``HF_HOME`` in the work folder:

1. export 2 seen tasks x 2 demos as a v3.0 LeRobot dataset (our CLI, front + wrist, 64 px,
   default layout: quaternion actions, RLBench state);
2. ``lerobot-train --policy.type=act --policy.pretrained_backbone_weights=null
   --policy.device=cpu --steps=20`` on it, ACT's chunk the export's longest episode and one
   action per step (``--policy.chunk_size=<longest> --policy.n_action_steps=1``; the
   padding share of ACT's default chunk of 100 and of this one recorded; loss logged every
   step: first and last recorded);
3. ``lerobot-eval --env.type=agnostos`` runs that checkpoint on 2 episodes of an unseen task
   without ``--env.cameras`` / ``--env.size``: the plug-in must take front + wrist at 64 px
   from the policy (the config lerobot-eval logs, the videos' frame size; exit status,
   LeRobot's eval_info.json, the episode videos' frame counts);
3b. the same with ``--env.size=224``, which the policy was not trained on: lerobot-eval must
   exit non-zero with one line naming the policy's inputs the env does not give;
4. LeRobot's own ``rollout()`` (scripts/lerobot_eval.py) drives the plug-in's envs, made by
   ``make_env`` after ``register_third_party_plugins()``, with a policy that replays each
   world's expert key actions (the export's action rows): LeRobot must count every episode
   of 3 seen tasks a success, in both autoreset modes (next_step reads
   ``info["is_success"]``, same_step ``info["final_info"]``).

Usage (repository root, our environment's Python for the export)::

    .venv/bin/python eval/reports/lerobot_interop/train_eval.py --lerobot-bin /tmp/lerobot-venv/bin

Writes train_eval.json next to this file; ``--keep DIR`` keeps the data and checkpoint.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import shlex
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
REPO = HERE.parents[2]

TASKS = ("open_drawer", "push_buttons")
CAMERAS = ("front", "wrist")
DEMOS, SIZE, STEPS = 2, 64, 20
EVAL_TASK = "lamp_on"  # unseen, level 1
REPLAY_TASKS = ("push_buttons", "turn_tap", "open_drawer")
LOSS = re.compile(r"step:(\d+) .*?\bloss:([0-9.]+)")

# Run by the lerobot Python: argv[1] = the json to write.
SIDE = r'''
import importlib.metadata as md, json, sys, time
import numpy as np, torch
from lerobot.envs.configs import EnvConfig
from lerobot.envs.factory import make_env
from lerobot.scripts.lerobot_eval import rollout
from lerobot.utils.import_utils import register_third_party_plugins

register_third_party_plugins()
out = {"known_env_types_has_agnostos": "agnostos" in EnvConfig.get_known_choices(),
       "versions": {n: md.version(n) for n in ("lerobot", "torch", "gymnasium", "numpy",
                                               "agnostos-mjx", "lerobot_env_agnostos")},
       "python": sys.version.split()[0], "replay": []}

class Replay(torch.nn.Module):
    """Each world's expert key actions as the export writes them, one per step."""
    def __init__(self, env):
        super().__init__()
        self.env, self.k = env, 0
    def reset(self):
        self.k = 0
    def select_action(self, batch):
        if self.k == 0:
            self.rows, _ = self.env.expert_actions()
        k = min(self.k, self.rows.shape[1] - 1)
        self.k += 1
        return torch.from_numpy(np.ascontiguousarray(self.rows[:, k]))

ident = lambda x: x
for mode in ("next_step", "same_step"):
    cfg = EnvConfig.get_choice_class("agnostos")(
        task=",".join(TASKS), cameras="front", size=32, autoreset_mode=mode)
    envs = make_env(cfg, n_envs=2, use_async_envs=True)
    pre, post = cfg.get_env_processors()
    for suite, group in envs.items():
        for task_id, env in group.items():
            t0 = time.perf_counter()
            data = rollout(env, Replay(env), pre, post, ident, ident, seeds=[0, 1])
            done_at = data["done"].int().argmax(1)
            out["replay"].append({
                "autoreset_mode": mode, "suite": suite, "task_id": task_id, "task": env.task,
                "successes": data["success"].any(1).tolist(),
                "steps_to_done": (done_at + 1).tolist(),
                "wall_s": round(time.perf_counter() - t0, 2)})
            env.close()
json.dump(out, open(sys.argv[1], "w"), indent=2)
'''


def run(cmd: list[str], env: dict, log: Path, cwd: Path = REPO) -> dict:
    """Run `cmd`, its output to `log`; exit status and wall time."""
    t0 = time.perf_counter()
    with open(log, "w") as f:
        proc = subprocess.run(cmd, env=env, cwd=cwd, stdout=f, stderr=subprocess.STDOUT)
    return {"command": shlex.join(cmd), "returncode": proc.returncode,
            "wall_s": round(time.perf_counter() - t0, 1)}


def tail(log: Path, lines: int = 15) -> list[str]:
    """The log's last lines, without the torchcodec/FFmpeg loading noise."""
    noise = ("torchcodec", "libav", "FFmpeg", "Traceback", "  File ", "OSError",
             "exception", "^", "[end of")
    keep = [ln.rstrip() for ln in log.read_text(errors="replace").splitlines()
            if ln.strip() and not any(n in ln for n in noise)]
    return keep[-lines:]


def video_frames(python: str, paths: list[str]) -> list[list[int]]:
    """Each video's [frames, width, height]."""
    code = ("import av, sys, json\nout = []\nfor p in sys.argv[1:]:\n"
            "    with av.open(p) as c:\n        s = c.streams.video[0]\n"
            "        out.append([sum(1 for _ in c.decode(s)), s.width, s.height])\n"
            "print(json.dumps(out))")
    proc = subprocess.run([python, "-c", code, *paths], capture_output=True, text=True)
    return json.loads(proc.stdout) if proc.returncode == 0 else []


def episode_lengths(dataset: Path) -> list[int]:
    """Frames per episode of a v3.0 export (meta/episodes)."""
    import pyarrow.parquet as pq

    return [int(n) for f in sorted((dataset / "meta/episodes").rglob("*.parquet"))
            for n in pq.read_table(f, columns=["length"])["length"].to_pylist()]


def padding(lengths: list[int], chunk: int) -> float:
    """Share of ACT's action targets that are padding: a frame t of an episode of L frames
    has min(chunk, L - t) real actions in its chunk."""
    real = sum(min(chunk, n - t) for n in lengths for t in range(n))
    return round(1 - real / (chunk * sum(lengths)), 3)


def logged_env(log: Path) -> dict:
    """The env config's cameras and size as lerobot-eval logs them (pformat of its config)."""
    text = log.read_text(errors="replace")
    found = {"cameras": re.search(r"'cameras': '([^']*)'", text),
             "size": re.search(r"'size': (\w+)", text)}
    return {k: m.group(1) for k, m in found.items() if m}


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--lerobot-bin", required=True,
                   help="bin/ of the venv with lerobot, agnostos-mjx and the plug-in")
    p.add_argument("--keep", help="keep the dataset, checkpoint and logs here")
    p.add_argument("--results", default=str(HERE / "train_eval.json"))
    a = p.parse_args()
    bin_ = Path(a.lerobot_bin)
    for tool in ("python", "lerobot-train", "lerobot-eval"):
        if not (bin_ / tool).exists():
            p.error(f"--lerobot-bin: no {tool} in {bin_}")
    work = Path(a.keep or tempfile.mkdtemp(prefix="lerobot_train_eval_"))
    work.mkdir(parents=True, exist_ok=True)
    env = {**os.environ, "HF_HUB_OFFLINE": "1", "HF_HOME": str(work / "hf_home"),
           "PYTHONPATH": str(REPO)}
    out: dict = {"date": time.strftime("%Y-%m-%d"), "work": str(work)}
    data = work / "agnostos_seen"
    shutil.rmtree(data, ignore_errors=True)
    shutil.rmtree(work / "train", ignore_errors=True)
    shutil.rmtree(work / "eval", ignore_errors=True)
    out["export"] = run([sys.executable, "-m", "agnostos_mjx.data.export", "--format", "lerobot",
                         "--tasks", ",".join(TASKS), "--demos", str(DEMOS), "--cameras",
                         ",".join(CAMERAS), "--size", str(SIZE), "--batch", "2", "--out",
                         str(data), "--quiet"], env, work / "export.log")
    out["export"]["command"] = out["export"]["command"].replace(sys.executable, "python")
    info = json.loads((data / "meta/info.json").read_text())
    lengths = episode_lengths(data)
    chunk = max(lengths)
    out["export"].update(episodes=info["total_episodes"], frames=info["total_frames"],
                         episode_lengths=lengths,
                         act_padding={"chunk 100 (ACT's default)": padding(lengths, 100),
                                      f"chunk {chunk} (longest episode)": padding(lengths, chunk)})
    train = [str(bin_ / "lerobot-train"), "--dataset.repo_id=local/agnostos_seen",
             f"--dataset.root={data}", "--policy.type=act",
             f"--policy.chunk_size={chunk}", "--policy.n_action_steps=1",
             "--policy.pretrained_backbone_weights=null", "--policy.device=cpu",
             "--policy.push_to_hub=false", f"--steps={STEPS}", "--batch_size=4",
             "--log_freq=1", f"--save_freq={STEPS}", "--num_workers=0",
             "--wandb.enable=false", f"--output_dir={work / 'train'}"]
    out["train"] = run(train, env, work / "train.log")
    losses = {int(s): float(v) for s, v in LOSS.findall((work / "train.log").read_text())}
    out["train"]["loss_by_step"] = [losses[k] for k in sorted(losses)]
    if losses:
        first, last = losses[min(losses)], losses[max(losses)]
        out["train"].update(first_loss=first, last_loss=last, loss_fell=last < first)
    ckpt = work / "train/checkpoints/last/pretrained_model"
    out["train"]["checkpoint_files"] = sorted(x.name for x in ckpt.glob("*")) if ckpt.exists() else []
    # no --env.cameras / --env.size: the plug-in takes the policy's
    evaluate = [str(bin_ / "lerobot-eval"), "--env.type=agnostos", f"--env.task={EVAL_TASK}",
                "--eval.n_episodes=2", "--eval.batch_size=2", f"--policy.path={ckpt}",
                "--policy.device=cpu", "--seed=0", f"--output_dir={work / 'eval'}"]
    out["eval"] = run(evaluate, env, work / "eval.log")
    out["eval"]["env_as_logged"] = logged_env(work / "eval.log")
    out["eval"]["log_tail"] = tail(work / "eval.log", 8)
    eval_info = work / "eval/eval_info.json"
    if eval_info.exists():
        overall = json.loads(eval_info.read_text())["overall"]
        out["eval"]["overall"] = {k: v for k, v in overall.items() if "video" not in k}
        out["eval"]["videos_frames_width_height"] = video_frames(str(bin_ / "python"),
                                                                 overall["video_paths"])
    # a size the policy was not trained on: one line, non-zero exit
    mismatch = [*evaluate[:3], "--env.size=224", *evaluate[3:-1],
                f"--output_dir={work / 'eval_224'}"]
    out["eval_224"] = run(mismatch, env, work / "eval_224.log")
    out["eval_224"]["last_line"] = tail(work / "eval_224.log", 1)
    side = work / "side.py"
    side.write_text(f"TASKS = {REPLAY_TASKS!r}\n" + SIDE)
    out["replay"] = run([str(bin_ / "python"), str(side), str(work / "side.json")], env,
                        work / "side.log")
    if (work / "side.json").exists():
        out["replay"].update(json.loads((work / "side.json").read_text()))
    else:
        out["replay"]["log_tail"] = tail(work / "side.log", 30)
    for step in ("export", "train", "eval"):
        if out[step]["returncode"]:
            out[step]["log_tail"] = tail(work / f"{step}.log", 30)
    Path(a.results).write_text(json.dumps(out, indent=2) + "\n")
    replays = out["replay"].get("replay", [])
    wanted = {"cameras": ",".join(CAMERAS), "size": str(SIZE)}
    frames = out["eval"].get("videos_frames_width_height", [])
    ok = (all(out[s]["returncode"] == 0 for s in ("export", "train", "eval", "replay"))
          and out["train"].get("loss_fell", False) and replays
          and all(all(r["successes"]) for r in replays)
          and out["eval"]["env_as_logged"] == wanted and frames
          and all(f[1:] == [SIZE, SIZE] for f in frames)
          and out["eval_224"]["returncode"] != 0
          and "observation.images.front (3, 64, 64)" in " ".join(out["eval_224"]["last_line"]))
    print(json.dumps({"ok": bool(ok), "first_loss": out["train"].get("first_loss"),
                      "last_loss": out["train"].get("last_loss"),
                      "eval_returncode": out["eval"]["returncode"],
                      "eval_env": out["eval"]["env_as_logged"],
                      "eval_224_returncode": out["eval_224"]["returncode"],
                      "replay_successes": [r["successes"] for r in replays]}))
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
