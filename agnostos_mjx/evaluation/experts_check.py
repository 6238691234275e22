"""Per-variation check of the scripted experts: every variation of every task
run on its own (``eval --policy oracle --variations N``), so that a variation
the expert fails cannot hide behind a task's average over sampled variations.

    python -m agnostos_mjx.evaluation.experts_check --tasks put_money_in_safe,water_plants
    python -m agnostos_mjx.evaluation.experts_check --tasks all --resume   # long on CPU

Writes ``<out>/runs/<task>/v<N>/`` (the eval outputs of each variation),
``<out>/results.json`` (one row per task and variation) and
``<out>/results.md`` (the table, rows under the threshold marked).
"""

from __future__ import annotations

import argparse
import json
import logging
from collections.abc import Sequence
from pathlib import Path

from agnostos_mjx.evaluation.config import parse_config
from agnostos_mjx.evaluation.records import load_records
from agnostos_mjx.evaluation.run import evaluate
from agnostos_mjx.infra.settings import configure_jax
from agnostos_mjx.tasks import parse_tasks

DEFAULT_OUT = Path("eval/reports/oracle_per_variation_cpu_2core")
THRESHOLD = 95.0  # % per variation, issue 14


def variation_row(task: str, split: str, variation: int, records: Sequence[dict]) -> dict:
    """Success rate (%) of one variation over all its episodes, per seed, and
    the failure outcomes."""
    seeds = sorted({r["seed"] for r in records})
    per_seed = {s: [r["success"] for r in records if r["seed"] == s] for s in seeds}
    failures: dict[str, int] = {}
    for r in records:
        if not r["success"]:
            failures[r["outcome"]] = failures.get(r["outcome"], 0) + 1
    return {
        "task": task, "split": split, "variation": variation, "episodes": len(records),
        "success": 100.0 * sum(r["success"] for r in records) / max(len(records), 1),
        "per_seed": {str(s): 100.0 * sum(v) / len(v) for s, v in per_seed.items()},
        "failures": dict(sorted(failures.items())),
    }


def format_table(rows: Sequence[dict], threshold: float = THRESHOLD) -> str:
    """Markdown table of the per-variation rows; rows under `threshold` are bold."""
    lines = ["| task | split | variation | episodes | success % | per seed | failures |",
             "|---|---|---|---|---|---|---|"]
    for r in rows:
        mark = "**" if r["success"] < threshold else ""
        seeds = ", ".join(f"{s}: {v:.0f}" for s, v in r["per_seed"].items())
        fails = ", ".join(f"{k}: {v}" for k, v in r["failures"].items()) or "-"
        lines.append(f"| {r['task']} | {r['split']} | {r['variation']} | {r['episodes']} | "
                     f"{mark}{r['success']:.1f}{mark} | {seeds} | {fails} |")
    below = [r for r in rows if r["success"] < threshold]
    lines += ["", f"{len(rows)} variations, {len(below)} under {threshold:.0f}%"
              + (": " + ", ".join(f"{r['task']} v{r['variation']}" for r in below)
                 if below else ".")]
    return "\n".join(lines) + "\n"


def run_variation(task: str, variation: int, run_dir: Path, seeds: str, episodes: int,
                  batch: int, backend: str, resume: bool) -> list[dict]:
    """One eval run of the oracle on a single variation; its episode records."""
    done = run_dir / "results.json"
    if not (resume and done.exists()):
        evaluate(parse_config([
            "--policy", "oracle", "--tasks", task, "--variations", str(variation),
            "--seeds", seeds, "--episodes", str(episodes), "--batch", str(batch),
            "--backend", backend, "--out", str(run_dir), "--quiet",
            *(["--resume"] if resume and (run_dir / "episodes.jsonl").exists() else []),
        ]))
    return load_records(run_dir / "episodes.jsonl")


def main(argv: Sequence[str] | None = None) -> int:
    configure_jax()
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    p.add_argument("--tasks", default="all", help="task names and/or split names, as in eval")
    p.add_argument("--variations", default=None,
                   help="comma-separated variations (default: all of each task)")
    p.add_argument("--seeds", default="0,1,2")
    p.add_argument("--episodes", type=int, default=25, help="episodes per seed and variation")
    p.add_argument("--batch", type=int, default=75)
    p.add_argument("--backend", default="native")
    p.add_argument("--out", type=Path, default=DEFAULT_OUT)
    p.add_argument("--resume", action="store_true",
                   help="keep finished variations in --out and their rows")
    args = p.parse_args(argv)
    logging.basicConfig(level=logging.WARNING)

    results = args.out / "results.json"
    rows = {(r["task"], r["variation"]): r
            for r in (json.loads(results.read_text())["rows"] if results.exists() else [])}
    for task in parse_tasks(args.tasks):
        wanted = (range(task.num_variations) if args.variations is None else
                  [int(v) for v in args.variations.split(",") if int(v) < task.num_variations])
        for v in wanted:
            records = run_variation(task.name, v, args.out / "runs" / task.name / f"v{v}",
                                    args.seeds, args.episodes, args.batch, args.backend,
                                    args.resume)
            rows[(task.name, v)] = variation_row(task.name, str(task.split.value), v, records)
            print(format_table([rows[(task.name, v)]]).splitlines()[2], flush=True)
            ordered = [rows[k] for k in sorted(rows)]
            results.write_text(json.dumps({"threshold": THRESHOLD, "rows": ordered}, indent=1))
            (args.out / "results.md").write_text(
                "## Scripted experts per variation (oracle policy, backend "
                f"{args.backend}, seeds {args.seeds}, {args.episodes} episodes per seed)\n\n"
                + format_table(ordered))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
