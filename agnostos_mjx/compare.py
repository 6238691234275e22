"""Compare two evaluation runs episode by episode: ``python -m agnostos_mjx.compare A B``.

Runs share their episodes' scenes when they share seeds (a scene depends only on task, seed
and episode index), so two runs pair up: two policies on the same scenes, or one policy on two
backends. For each task the table gives both success rates over the shared episodes, the
difference, how many episodes only one run solved (the discordant pairs that a paired test
looks at) and how many episodes ended identically (same outcome, key-action count and
simulation steps: a reproducibility check, which native MuJoCo passes bit for bit).

    python -m agnostos_mjx.compare eval/reports/default_dynamics_h200/native \\
        eval/reports/default_dynamics_h200/warp --labels native,warp --out diff.md
"""

from __future__ import annotations

import argparse
import gzip
import json
import sys
from collections.abc import Sequence
from pathlib import Path

from agnostos_mjx.cli import HelpFormatter, atomic_write
from agnostos_mjx.evaluation.protocol import group_label
from agnostos_mjx.evaluation.records import EPISODES_FILE
from agnostos_mjx.evaluation.summary import aggregate

Key = tuple[str, int, int]


class CompareError(ValueError):
    """A run folder that cannot be compared (missing, empty or unreadable)."""


def load_episodes(run: Path) -> list[dict]:
    """Episode records of an evaluation folder (episodes.jsonl, or the .gz kept in reports)."""
    for name in (EPISODES_FILE, EPISODES_FILE + ".gz"):
        path = run / name
        if path.exists():
            opener = gzip.open if name.endswith(".gz") else open
            try:
                with opener(path, "rt", encoding="utf-8") as f:
                    records = [json.loads(line) for line in f if line.strip()]
            except (OSError, json.JSONDecodeError, EOFError) as e:
                raise CompareError(f"{path} is unreadable: {e}") from None
            if not records:
                raise CompareError(f"{path} holds no episodes")
            return records
    raise CompareError(f"{run} has no {EPISODES_FILE}(.gz): not an agnostos_mjx.eval output folder")


def _key(r: dict) -> Key:
    return r["task"], int(r["seed"]), int(r["episode"])


def _same_end(a: dict, b: dict) -> bool:
    return all(a.get(k) == b.get(k) for k in ("outcome", "key_actions", "sim_steps"))


def compare(a: Sequence[dict], b: Sequence[dict]) -> dict:
    """Paired comparison over the episodes both runs hold; see the module docstring."""
    a_by, b_by = {_key(r): r for r in a}, {_key(r): r for r in b}
    shared = [k for k in a_by if k in b_by]
    if not shared:
        raise CompareError("the runs share no (task, seed, episode): nothing to compare")
    tasks = list(dict.fromkeys(k[0] for k in shared))
    sum_a = aggregate([a_by[k] for k in shared], tasks)
    sum_b = aggregate([b_by[k] for k in shared], tasks)
    rows = {}
    for task in tasks:
        keys = [k for k in shared if k[0] == task]
        wins_a = sum(bool(a_by[k]["success"]) and not b_by[k]["success"] for k in keys)
        wins_b = sum(bool(b_by[k]["success"]) and not a_by[k]["success"] for k in keys)
        ta, tb = sum_a["tasks"][task], sum_b["tasks"][task]
        rows[task] = {"split": ta["split"], "episodes": len(keys),
                      "a": ta["success_mean"], "b": tb["success_mean"],
                      "a_std": ta["success_std"], "b_std": tb["success_std"],
                      "only_a": wins_a, "only_b": wins_b,
                      "identical": sum(_same_end(a_by[k], b_by[k]) for k in keys)}
    groups = {g: {"a": sum_a["groups"][g]["success_mean"], "b": sum_b["groups"][g]["success_mean"],
                  "a_std": sum_a["groups"][g]["success_std"],
                  "b_std": sum_b["groups"][g]["success_std"],
                  "tasks": len(sum_a["groups"][g]["tasks"])}
              for g in sum_a["groups"]}
    return {"shared_episodes": len(shared), "only_in_a": len(a_by) - len(shared),
            "only_in_b": len(b_by) - len(shared), "tasks": rows, "groups": groups}


def format_markdown(result: dict, labels: tuple[str, str]) -> str:
    la, lb = labels
    lines = [f"## {la} vs {lb}: {result['shared_episodes']} shared episodes"
             + (f" ({result['only_in_a']} only in {la}, {result['only_in_b']} only in {lb})"
                if result["only_in_a"] or result["only_in_b"] else ""), "",
             f"| task | split | episodes | {la} % | {lb} % | {lb} - {la} | solved only by {la} "
             f"| solved only by {lb} | ended identically |",
             "|---|---|---|---|---|---|---|---|---|"]
    for task, r in result["tasks"].items():
        lines.append(f"| {task} | {r['split']} | {r['episodes']} | {r['a']:.1f} | {r['b']:.1f} "
                     f"| {r['b'] - r['a']:+.1f} | {r['only_a']} | {r['only_b']} "
                     f"| {r['identical']} |")
    if result["groups"]:
        lines += ["", f"| group | tasks | {la} % mean (std) | {lb} % mean (std) | {lb} - {la} |",
                  "|---|---|---|---|---|"]
        for name, g in result["groups"].items():
            lines.append(f"| {group_label(name)} | {g['tasks']} "
                         f"| {g['a']:.1f} ({g['a_std']:.1f}) | {g['b']:.1f} ({g['b_std']:.1f}) "
                         f"| {g['b'] - g['a']:+.1f} |")
    same = sum(r["identical"] for r in result["tasks"].values())
    lines += ["", f"{same} of {result['shared_episodes']} shared episodes ended identically."]
    return "\n".join(lines) + "\n"


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="python -m agnostos_mjx.compare", formatter_class=HelpFormatter,
                                description=__doc__.split("\n\n")[0])
    p.add_argument("run_a", type=Path, help="first evaluation folder (holds episodes.jsonl[.gz])")
    p.add_argument("run_b", type=Path, help="second evaluation folder")
    p.add_argument("--labels", default=None,
                   help="comma-separated names of the two runs (default: the folder names)")
    p.add_argument("--out", type=Path, default=None,
                   help="also write the Markdown table here, and the numbers as JSON beside it")
    return p


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    labels = tuple(args.labels.split(",")) if args.labels else (args.run_a.name, args.run_b.name)
    if len(labels) != 2 or not all(labels):
        print(f"error: --labels needs two comma-separated names, got {args.labels!r}",
              file=sys.stderr)
        return 2
    try:
        result = compare(load_episodes(args.run_a), load_episodes(args.run_b))
    except CompareError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    text = format_markdown(result, labels)
    print(text, end="")
    if args.out:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        atomic_write(args.out, text)
        atomic_write(args.out.with_suffix(".json"),
                     json.dumps({"labels": labels, **result}, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
