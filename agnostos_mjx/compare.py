"""Compare two evaluation runs episode by episode: ``python -m agnostos_mjx.compare A B``.

Runs share their episodes' scenes when they share seeds (a scene depends only on task, seed
and episode index), so two runs pair up: two policies on the same scenes, or one policy on two
backends. For each task the table gives both success rates over the shared episodes, the
difference, how many episodes only one run solved (the discordant pairs that a paired test
looks at) and how many episodes ended identically (same outcome, key-action count and
simulation steps: a reproducibility check, which native MuJoCo passes bit for bit).

A statistics section follows (agnostos_mjx.infra.stats): per task both success rates with Wilson 95 %
intervals, and McNemar's exact p on the discordant pairs (* marks p < 0.05, uncorrected); per
group (Level-1, Level-2, All (unseen), Seen) the difference B - A with a 95 % interval from a
bootstrap that resamples episodes within tasks.  A task is compared paired over the episodes
both runs hold; episodes only one run holds are counted and left out.  A task the runs share
but with no common episode (other seeds or episode indices) falls back to unpaired reporting:
each run's own episodes, no McNemar test, an unpaired bootstrap.  The report says so.

    python -m agnostos_mjx.compare runs/native runs/warp --labels native,warp --out diff.md

Success rates are in percent in the tables and the JSON; p-values are fractions.
"""

from __future__ import annotations

import argparse
import gzip
import json
import sys
from collections.abc import Sequence
from pathlib import Path

from agnostos_mjx.evaluation.protocol import GROUPS, group_label
from agnostos_mjx.evaluation.records import EPISODES_FILE
from agnostos_mjx.evaluation.summary import aggregate
from agnostos_mjx.infra.cli import HelpFormatter, atomic_write, prog
from agnostos_mjx.infra.stats import (
    Pairing,
    bootstrap_difference,
    mcnemar_exact,
    pair_records,
    wilson_interval,
)

ALPHA = 0.05  # the significance mark of the task table


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


def _same_end(a: dict, b: dict) -> bool:
    return all(a.get(k) == b.get(k) for k in ("outcome", "key_actions", "sim_steps"))


def compare(a: Sequence[dict], b: Sequence[dict], n_boot: int = 10000, seed: int = 0) -> dict:
    """Paired comparison over the episodes both runs hold, then the statistics section
    (`statistics`); see the module docstring.  Raises CompareError if the runs share no task."""
    pairing = pair_records(a, b)
    tasks_a = list(dict.fromkeys(r["task"] for r in a))
    tasks_b = set(r["task"] for r in b)
    if not any(t in tasks_b for t in tasks_a):
        raise CompareError("the runs share no task: nothing to compare")
    shared = list(pairing.pairs)
    tasks = pairing.tasks()
    sum_a = aggregate([pairing.pairs[k][0] for k in shared], tasks)
    sum_b = aggregate([pairing.pairs[k][1] for k in shared], tasks)
    rows = {}
    for task in tasks:
        pairs = [pairing.pairs[k] for k in shared if k[0] == task]
        wins_a = sum(bool(ra["success"]) and not rb["success"] for ra, rb in pairs)
        wins_b = sum(bool(rb["success"]) and not ra["success"] for ra, rb in pairs)
        ta, tb = sum_a["tasks"][task], sum_b["tasks"][task]
        rows[task] = {"split": ta["split"], "episodes": len(pairs),
                      "a": ta["success_mean"], "b": tb["success_mean"],
                      "a_std": ta["success_std"], "b_std": tb["success_std"],
                      "only_a": wins_a, "only_b": wins_b,
                      "identical": sum(_same_end(ra, rb) for ra, rb in pairs)}
    groups = {g: {"a": sum_a["groups"][g]["success_mean"], "b": sum_b["groups"][g]["success_mean"],
                  "a_std": sum_a["groups"][g]["success_std"],
                  "b_std": sum_b["groups"][g]["success_std"],
                  "tasks": len(sum_a["groups"][g]["tasks"])}
              for g in sum_a["groups"]}
    return {"shared_episodes": len(shared), "only_in_a": len(pairing.only_a),
            "only_in_b": len(pairing.only_b), "tasks": rows, "groups": groups,
            "statistics": statistics(a, b, pairing, n_boot=n_boot, seed=seed)}


def _pct(x: float) -> float:
    return 100.0 * float(x)


def statistics(a: Sequence[dict], b: Sequence[dict], pairing: Pairing | None = None,
               n_boot: int = 10000, seed: int = 0) -> dict:
    """Per task: success rates (%) with Wilson 95 % intervals, discordant counts and McNemar's
    exact p; per group: B - A (% points) with a stratified bootstrap 95 % interval.

    A task the runs share is "paired" when they hold common episodes (the statistics then use
    those pairs only; its other episodes are counted in `left_out`), else "unpaired" (each
    run's own episodes; no McNemar p, an unpaired bootstrap)."""
    pairing = pairing or pair_records(a, b)
    by_task_a: dict[str, list[dict]] = {}
    by_task_b: dict[str, list[dict]] = {}
    for r in a:
        by_task_a.setdefault(r["task"], []).append(r)
    for r in b:
        by_task_b.setdefault(r["task"], []).append(r)
    common = [t for t in by_task_a if t in by_task_b]
    pairs_by_task: dict[str, list[tuple[dict, dict]]] = {}
    for k, pair in pairing.pairs.items():
        pairs_by_task.setdefault(k[0], []).append(pair)
    unpaired_by_task: dict[str, int] = {}
    for k in pairing.only_a + pairing.only_b:
        unpaired_by_task[k[0]] = unpaired_by_task.get(k[0], 0) + 1

    outcomes_a: dict[str, list[bool]] = {}
    outcomes_b: dict[str, list[bool]] = {}
    rows: dict[str, dict] = {}
    for task in common:
        pairs = pairs_by_task.get(task)
        if pairs:
            sa = [bool(ra["success"]) for ra, _ in pairs]
            sb = [bool(rb["success"]) for _, rb in pairs]
            only_a = sum(x and not y for x, y in zip(sa, sb))
            only_b = sum(y and not x for x, y in zip(sa, sb))
            p: float | None = mcnemar_exact(only_a, only_b)
            left_out = unpaired_by_task.get(task, 0)
        else:
            sa = [bool(r["success"]) for r in by_task_a[task]]
            sb = [bool(r["success"]) for r in by_task_b[task]]
            only_a = only_b = None
            p = None
            left_out = 0
        outcomes_a[task], outcomes_b[task] = sa, sb
        (a_lo, a_hi), (b_lo, b_hi) = wilson_interval(sum(sa), len(sa)), wilson_interval(sum(sb), len(sb))
        rows[task] = {"split": by_task_a[task][0]["split"],
                      "pairing": "paired" if pairs else "unpaired",
                      "n_a": len(sa), "n_b": len(sb), "left_out": left_out,
                      "a": _pct(sum(sa) / len(sa)), "a_low": _pct(a_lo), "a_high": _pct(a_hi),
                      "b": _pct(sum(sb) / len(sb)), "b_low": _pct(b_lo), "b_high": _pct(b_hi),
                      "only_a": only_a, "only_b": only_b, "p": p,
                      "significant": p is not None and p < ALPHA}

    groups: dict[str, dict] = {}
    for name, splits in GROUPS:
        members = [t for t in common if rows[t]["split"] in splits]
        if not members:
            continue
        paired = [t for t in members if rows[t]["pairing"] == "paired"]
        diff, low, high = bootstrap_difference({t: outcomes_a[t] for t in members},
                                               {t: outcomes_b[t] for t in members},
                                               paired=paired, n_boot=n_boot, seed=seed)
        mode = ("paired" if len(paired) == len(members) else "unpaired" if not paired
                else f"mixed ({len(paired)} of {len(members)} tasks paired)")
        groups[name] = {"tasks": len(members), "pairing": mode,
                        "a": sum(rows[t]["a"] for t in members) / len(members),
                        "b": sum(rows[t]["b"] for t in members) / len(members),
                        "diff": _pct(diff), "diff_low": _pct(low), "diff_high": _pct(high)}
    return {"fully_paired": pairing.fully_paired, "paired_episodes": len(pairing.pairs),
            "unpaired_episodes": pairing.unpaired,
            "unpaired_only_in_a": len(pairing.only_a), "unpaired_only_in_b": len(pairing.only_b),
            "duplicates": {"a": pairing.duplicates_a, "b": pairing.duplicates_b},
            "unpaired_tasks": [t for t in common if rows[t]["pairing"] == "unpaired"],
            "tasks_only_in_a": [t for t in by_task_a if t not in by_task_b],
            "tasks_only_in_b": [t for t in by_task_b if t not in by_task_a],
            "significant": [t for t in common if rows[t]["significant"]],
            "alpha": ALPHA, "bootstrap": {"samples": n_boot, "seed": seed, "level": 0.95},
            "tasks": rows, "groups": groups}


def format_markdown(result: dict, labels: tuple[str, str]) -> str:
    la, lb = labels
    lines = [f"## {la} vs {lb}: {result['shared_episodes']} shared episodes"
             + (f" ({result['only_in_a']} only in {la}, {result['only_in_b']} only in {lb})"
                if result["only_in_a"] or result["only_in_b"] else ""), ""]
    if result["shared_episodes"]:
        lines += [f"| task | split | episodes | {la} % | {lb} % | {lb} - {la} | solved only by {la} "
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
    else:
        lines.append("The runs share no episode (task, seed, episode): nothing to compare "
                     "episode by episode.")
    text = "\n".join(lines) + "\n"
    if "statistics" in result:
        text += "\n" + format_statistics(result["statistics"], labels)
    return text


def _interval(value: float, low: float, high: float, sign: str = "") -> str:
    return f"{value:{sign}.1f} [{low:{sign}.1f}, {high:{sign}.1f}]"


def _pairing_note(st: dict, la: str, lb: str) -> list[str]:
    if st["fully_paired"]:
        return [f"All {st['paired_episodes']} episodes pair up by (task, seed, episode): "
                f"paired statistics throughout."]
    n = st["unpaired_episodes"]
    lines = [f"**The runs are not fully paired:** {n} episode{' is' if n == 1 else 's are'} unpaired "
             f"({st['unpaired_only_in_a']} only in {la}, {st['unpaired_only_in_b']} only in {lb}; "
             f"{st['paired_episodes']} paired)."]
    left_out = sum(r["left_out"] for r in st["tasks"].values() if r["pairing"] == "paired")
    if left_out:
        lines.append(f"- Paired tasks use their common episodes only: {left_out} unpaired "
                     f"episode{'' if left_out == 1 else 's'} of them left out of the statistics.")
    if st["unpaired_tasks"]:
        lines.append(f"- No common episode (other seeds or episodes), so compared unpaired on each "
                     f"run's own episodes, without McNemar's test: "
                     f"{', '.join(st['unpaired_tasks'])}.")
    for label, key in ((la, "tasks_only_in_a"), (lb, "tasks_only_in_b")):
        if st[key]:
            lines.append(f"- Only in {label} (not compared): {', '.join(st[key])}.")
    return lines


def format_statistics(st: dict, labels: tuple[str, str]) -> str:
    """The statistics section (see `statistics`) as Markdown."""
    la, lb = labels
    lines = [f"### Statistics: {la} vs {lb}, 95 % intervals", "", *_pairing_note(st, la, lb)]
    dup = st["duplicates"]
    if dup["a"] or dup["b"]:
        lines.append(f"- Repeated (task, seed, episode) records ignored (first kept): "
                     f"{dup['a']} in {la}, {dup['b']} in {lb}.")
    lines += ["", f"| task | split | pairing | episodes | {la} % [Wilson 95%] | {lb} % [Wilson 95%] "
              f"| solved only by {la} | solved only by {lb} | McNemar p | p < {st['alpha']:g} |",
              "|---|---|---|---|---|---|---|---|---|---|"]
    for task, r in st["tasks"].items():
        n = str(r["n_a"]) if r["pairing"] == "paired" else f"{r['n_a']} / {r['n_b']}"
        only = (f"{r['only_a']} | {r['only_b']}" if r["p"] is not None else "- | -")
        p = f"{r['p']:.3g}" if r["p"] is not None else "-"
        lines.append(f"| {task} | {r['split']} | {r['pairing']} | {n} "
                     f"| {_interval(r['a'], r['a_low'], r['a_high'])} "
                     f"| {_interval(r['b'], r['b_low'], r['b_high'])} | {only} | {p} "
                     f"| {'*' if r['significant'] else ''} |")
    tested = sum(r["p"] is not None for r in st["tasks"].values())
    sig = st["significant"]
    if tested:
        lines += ["", (f"p < {st['alpha']:g}: {', '.join(sig)}" if sig
                       else f"No task differs at p < {st['alpha']:g}")
                  + f" (McNemar's exact test on the discordant episodes of each of {tested} paired "
                    f"tasks, not corrected for multiple comparisons)."]
    else:
        lines += ["", "No McNemar test: no task has episodes both runs hold."]
    if st["groups"]:
        boot = st["bootstrap"]
        lines += ["", f"| group | tasks | pairing | {la} % | {lb} % | {lb} - {la} [95% CI] |",
                  "|---|---|---|---|---|---|"]
        for name, g in st["groups"].items():
            lines.append(f"| {group_label(name)} | {g['tasks']} | {g['pairing']} | {g['a']:.1f} "
                         f"| {g['b']:.1f} | {_interval(g['diff'], g['diff_low'], g['diff_high'], '+')} |")
        lines += ["", f"Group rates are means over tasks; the interval is the percentile interval of "
                      f"{boot['samples']} bootstrap resamples of episodes within each task "
                      f"(paired tasks resample pairs; seed {boot['seed']})."]
    return "\n".join(lines) + "\n"


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog=prog("agnostos_mjx.compare"), formatter_class=HelpFormatter,
                                description=__doc__.split("\n\n")[0])
    p.add_argument("run_a", type=Path, help="first evaluation folder (holds episodes.jsonl[.gz])")
    p.add_argument("run_b", type=Path, help="second evaluation folder")
    p.add_argument("--labels", default=None,
                   help="comma-separated names of the two runs (default: the folder names)")
    p.add_argument("--out", type=Path, default=None,
                   help="also write the Markdown table here, and the numbers as JSON beside it")
    p.add_argument("--json", type=Path, default=None, dest="json_path", metavar="PATH",
                   help="write the numbers (both tables and the statistics) as JSON here")
    p.add_argument("--bootstrap-samples", type=int, default=10000, metavar="N",
                   help="bootstrap resamples for the groups' difference intervals")
    p.add_argument("--bootstrap-seed", type=int, default=0, metavar="SEED",
                   help="seed of the bootstrap (the same seed gives the same intervals)")
    return p


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    labels = tuple(args.labels.split(",")) if args.labels else (args.run_a.name, args.run_b.name)
    if len(labels) != 2 or not all(labels):
        print(f"error: --labels needs two comma-separated names, got {args.labels!r}",
              file=sys.stderr)
        return 2
    try:
        if args.bootstrap_samples < 1:
            raise CompareError(f"--bootstrap-samples must be >= 1, got {args.bootstrap_samples}")
        result = compare(load_episodes(args.run_a), load_episodes(args.run_b),
                         n_boot=args.bootstrap_samples, seed=args.bootstrap_seed)
    except CompareError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    text = format_markdown(result, labels)
    print(text, end="")
    numbers = json.dumps({"labels": labels, **result}, indent=1) + "\n"
    if args.out:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        atomic_write(args.out, text)
        atomic_write(args.out.with_suffix(".json"), numbers)
    if args.json_path:
        args.json_path.parent.mkdir(parents=True, exist_ok=True)
        atomic_write(args.json_path, numbers)
    return 0


if __name__ == "__main__":
    sys.exit(main())
