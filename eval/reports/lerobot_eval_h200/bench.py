"""``lerobot-eval`` through the agnostos plug-in, timed on each renderer route.

Run with a Python that has lerobot (>= 0.6), the plug-in and agnostos_mjx:

    python eval/reports/lerobot_eval_h200/bench.py --dataset DS --out OUT \
        [--lerobot-eval lerobot-eval] [--renderers cpu,auto] [--envs 75] [--steps 20,220]

1. Builds an ACT policy for the dataset's features (cameras, state, action) with its
   statistics, untrained (random weights, no pretrained backbone: nothing is downloaded),
   and saves it with its processors as ``lerobot-train`` saves a checkpoint.  Its actions
   are the dataset's mean plus noise, so no episode succeeds and every one runs its whole
   budget: the env's cost, not the policy's skill, sets the time.
2. Runs ``lerobot-eval --env.type=agnostos --policy.path=OUT/act`` per route
   (``--env.renderer``), dense control, ``--envs`` worlds, with LeRobot's defaults
   otherwise (its first 10 episodes are recorded as videos): first a 2-step run (the
   route's programs and kernels built and cached), then one run per ``--steps`` budget.
3. Writes OUT/results.json: per run the command's wall and LeRobot's own ``eval_s``
   (from the envs' first reset to the last episode's end); per route the env steps/s
   between the two budgets (worlds x extra steps / extra eval_s: the steady rate, without
   the reset and the first step's compiles) and its ratio to the first route's.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path


def make_policy(dataset: Path, out: Path, device: str) -> None:
    """An untrained ACT for `dataset`'s features and stats, saved to `out`."""
    import numpy as np
    import torch
    from lerobot.configs.types import FeatureType, PolicyFeature
    from lerobot.policies.act.configuration_act import ACTConfig
    from lerobot.policies.act.modeling_act import ACTPolicy
    from lerobot.policies.factory import make_pre_post_processors

    info = json.loads((dataset / "meta" / "info.json").read_text())
    stats = json.loads((dataset / "meta" / "stats.json").read_text())
    inputs, outputs = {}, {}
    for key, ft in info["features"].items():
        shape = tuple(ft["shape"])
        if key.startswith("observation.images."):
            inputs[key] = PolicyFeature(FeatureType.VISUAL, (shape[2], shape[0], shape[1]))
        elif key == "observation.state":
            inputs[key] = PolicyFeature(FeatureType.STATE, shape)
        elif key == "action":
            outputs[key] = PolicyFeature(FeatureType.ACTION, shape)
    torch.manual_seed(0)
    cfg = ACTConfig(input_features=inputs, output_features=outputs, chunk_size=24,
                    n_action_steps=1, pretrained_backbone_weights=None, device=device,
                    push_to_hub=False)
    policy = ACTPolicy(cfg)
    tensors = {key: {name: torch.as_tensor(np.asarray(value, np.float32))
                     for name, value in stat.items()}
               for key, stat in stats.items() if key in inputs or key in outputs}
    pre, post = make_pre_post_processors(cfg, dataset_stats=tensors)
    out.mkdir(parents=True, exist_ok=True)
    policy.save_pretrained(out)
    pre.save_pretrained(out)
    post.save_pretrained(out)


def run_eval(args: argparse.Namespace, renderer: str, steps: int) -> dict:
    """One lerobot-eval command: its wall, eval_s and success rate."""
    name = f"eval_{renderer}_{steps}"
    out = args.out / name
    cmd = [args.lerobot_eval, "--env.type=agnostos", f"--env.task={args.task}",
           "--env.control_mode=dense", f"--env.dense_steps={steps}",
           f"--env.renderer={renderer}", f"--eval.n_episodes={args.envs}",
           f"--eval.batch_size={args.envs}", f"--policy.path={args.out / 'act'}",
           f"--policy.device={args.device}", "--seed=0", f"--output_dir={out}"]
    t = time.perf_counter()
    proc = subprocess.run(cmd, capture_output=True, text=True, env=os.environ)
    wall = time.perf_counter() - t
    (args.out / f"{name}.log").write_text(proc.stdout + proc.stderr)
    row = {"renderer": renderer, "steps": steps, "command": " ".join(cmd),
           "rc": proc.returncode, "command_s": round(wall, 2)}
    if proc.returncode != 0:
        print(f"{name}: exit {proc.returncode}; log {args.out / f'{name}.log'}",
              file=sys.stderr)
        return row
    overall = json.loads((out / "eval_info.json").read_text())["overall"]
    row.update(eval_s=round(overall["eval_s"], 2), pc_success=overall.get("pc_success"))
    print(json.dumps({k: v for k, v in row.items() if k != "command"}), flush=True)
    return row


def steady_rate(runs: list[dict], envs: int) -> float | None:
    """Env steps/s between a route's smallest and largest budget."""
    done = sorted((r for r in runs if r["rc"] == 0), key=lambda r: r["steps"])
    if len(done) < 2 or done[-1]["eval_s"] <= done[0]["eval_s"]:
        return None
    extra_steps = envs * (done[-1]["steps"] - done[0]["steps"])
    return round(extra_steps / (done[-1]["eval_s"] - done[0]["eval_s"]), 1)


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--dataset", type=Path, required=True,
                   help="a LeRobot export (python -m agnostos_mjx.data.export --format lerobot)")
    p.add_argument("--out", type=Path, required=True, help="work folder; results.json here")
    p.add_argument("--lerobot-eval", default="lerobot-eval", help="the lerobot-eval command")
    p.add_argument("--renderers", default="cpu,auto", help="routes; the first is the base")
    p.add_argument("--task", default="lamp_on", help="the env's task")
    p.add_argument("--envs", type=int, default=75, help="episodes, all in one batch")
    p.add_argument("--steps", default="20,220",
                   help="dense control budgets an episode, comma-separated (two or more)")
    p.add_argument("--device", default="cuda", help="the policy's torch device")
    args = p.parse_args()
    budgets = [int(x) for x in args.steps.split(",")]
    if len(budgets) < 2 or min(budgets) < 1:
        p.error("--steps needs two or more positive budgets")
    make_policy(args.dataset, args.out / "act", args.device)
    routes, runs = [], []
    for renderer in args.renderers.split(","):
        run_eval(args, renderer, 2)  # builds and caches the route's programs
        mine = [run_eval(args, renderer, steps) for steps in budgets]
        runs += mine
        routes.append({"renderer": renderer, "env_steps_per_s": steady_rate(mine, args.envs)})
    base = routes[0]["env_steps_per_s"]
    for route in routes:
        if base and route["env_steps_per_s"]:
            route["ratio"] = round(route["env_steps_per_s"] / base, 2)
        print(json.dumps(route))
    (args.out / "results.json").write_text(json.dumps(
        {"envs": args.envs, "task": args.task, "routes": routes, "runs": runs}, indent=1) + "\n")
    return 0 if all(r["rc"] == 0 for r in runs) else 1


if __name__ == "__main__":
    sys.exit(main())
