"""One-off: does the real LeRobot read our LeRobot export as it is?

Exports 2 seen tasks x 2 demos with ``python -m agnostos_mjx.data.export --format lerobot``
(front + wrist, 64 px, default layout: quaternion actions, RLBench state) as v3.0, then as
v2.1 from the same staged demos (nothing rendered twice), and reads both back with our
``read_lerobot``.  Then, in other Pythons that have lerobot:

* ``--lerobot-python`` (lerobot >= 0.4, v3.0; last checked with 0.6.1):
  ``LeRobotDataset(repo_id, root=...)`` on the v3.0 export; and LeRobot's
  ``convert_dataset_v21_to_v30`` on a copy of the v2.1 export, read with
  ``LeRobotDataset``, and its files compared here with our v3.0 export's (data
  rows with the PNG bytes, column types, metadata, statistics) and given to our reader;
* ``--lerobot21-python`` (lerobot 0.3.3, v2.1, openpi's): ``LeRobotDataset`` on the v2.1
  export.

LeRobot's side is the opt-in test's (tests/test_lerobot_export.py ``LEROBOT_SIDE``: every
item with ``delta_timestamps`` action chunks of 3, dumped to .npz) plus a few lines that
dump the versions and LeRobot's own statistics.  Every frame is compared with our reader's:
images (LeRobot's float CHW tensor, exactly ours / 255 and back to the same uint8), state,
the action chunk and its padding flags, timestamp, indices and task.  All runs under
``HF_HUB_OFFLINE=1`` with ``HF_HOME`` in the work folder.

Usage (repository root, our environment; the lerobot Pythons are commands, so a
``PYTHONPATH`` can come along; the README says how each was set up)::

    .venv/bin/python eval/reports/lerobot_interop/check.py \\
        --lerobot-python /tmp/lerobot-venv/bin/python            # lerobot 0.6.1
    .venv/bin/python eval/reports/lerobot_interop/check.py \\
        --lerobot-python "env PYTHONPATH=/tmp/tvstub /tmp/lrvenv/bin/python" \\
        --lerobot21-python "env PYTHONPATH=/tmp/lr033:/tmp/tvstub /tmp/lrvenv/bin/python" \\
        --results eval/reports/lerobot_interop/results_lerobot044_033.json  # 0.4.4, 0.3.3

Prints a summary and writes results.json next to this file (``--results`` elsewhere); ``--keep DIR`` keeps the data.
"""

from __future__ import annotations

import argparse
import json
import os
import shlex
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
REPO = HERE.parents[2]
sys.path.insert(0, str(REPO))

TASKS = ("open_drawer", "push_buttons")
CAMERAS = ("front", "wrist")
DEMOS, SIZE, CHUNK = 2, 64, 3  # CHUNK: the side's delta_timestamps, actions t .. t+2
SCALARS = ("timestamp", "frame_index", "episode_index", "index", "task_index")

# Appended to the test's LEROBOT_SIDE (which leaves root, out, meta, ds defined).
SIDE_EXTRA = r'''
import importlib.metadata as _md
import json
import lerobot
import torchvision
from lerobot.datasets import lerobot_dataset as _ld


def _version(name):
    try:
        return _md.version(name)
    except _md.PackageNotFoundError:
        return None


json.dump({"python": sys.version.split()[0], "codebase_version": _ld.CODEBASE_VERSION,
           **{n: _version(n) for n in ("lerobot", "datasets", "torch", "huggingface_hub",
                                       "pyarrow", "pandas", "numpy")},
           "torchvision": torchvision.__version__, "lerobot_file": lerobot.__file__,
           "torchvision_file": torchvision.__file__,
           "info": meta.info if isinstance(meta.info, dict) else meta.info.to_dict(),  # >= 0.5
           "num_episodes": ds.num_episodes,
           "stats": {f: {s: np.asarray(v).tolist() for s, v in st.items()}
                     for f, st in meta.stats.items()}}, open(out + ".json", "w"))
'''


def side_script() -> str:
    from tests.test_lerobot_export import LEROBOT_SIDE

    return LEROBOT_SIDE + SIDE_EXTRA


# ---- comparisons ------------------------------------------------------------------------------
def compare_lerobot(d, ours: list[dict]) -> dict:
    """LeRobotDataset's items (the side's dump) against our reader's frames: rows that
    differ, per field."""
    n = len(ours)
    if len(d["index"]) != n:
        return {"frames": int(len(d["index"])), "ours": n, "equal": False}
    diff: dict[str, int] = {}
    rows = lambda bad: int(np.count_nonzero(bad.reshape(n, -1).any(1)))  # noqa: E731
    for cam in CAMERAS:
        key = f"observation.images.{cam}"
        want = np.stack([f[key] for f in ours]).transpose(0, 3, 1, 2)  # uint8 CHW
        got = d[key]
        diff[key] = rows(got != want.astype(np.float32) / np.float32(255))
        diff[f"{key} (as uint8)"] = rows(np.round(got * 255).astype(np.uint8) != want)
    state = np.stack([f["observation.state"] for f in ours])
    diff["observation.state"] = rows(d["observation.state"] != state)
    for key in SCALARS:
        diff[key] = rows(d[key] != np.array([f[key] for f in ours], d[key].dtype))
    diff["task"] = rows(np.array([a != f["task"] for a, f in zip(d["task"], ours)]))
    ep = np.array([f["episode_index"] for f in ours])
    actions = np.stack([f["action"] for f in ours])
    bad = np.zeros(n, bool)
    for i in range(n):
        for k in range(CHUNK):
            pad = i + k >= n or ep[i + k] != ep[i]
            bad[i] |= bool(d["action_is_pad"][i, k]) != pad
            bad[i] |= not pad and not np.array_equal(d["action"][i, k], actions[i + k])
    diff[f"action (chunks of {CHUNK}, padding)"] = int(bad.sum())
    return {"frames": n, "episodes": int(len(set(ep))), "images_compared": n * len(CAMERAS),
            "rows_that_differ": diff, "equal": not any(diff.values())}


def stats_diff(a: dict, b: dict) -> dict:
    """Max |a - b| over the statistics both name, overall and by statistic (min, q01, ...);
    the names only one has."""
    by_stat: dict[str, float] = {}
    worst, where, only = 0.0, None, []
    for feat in sorted(set(a) | set(b)):
        for stat in sorted(set(a.get(feat, {})) | set(b.get(feat, {}))):
            if stat not in a.get(feat, {}) or stat not in b.get(feat, {}):
                only.append(f"{feat}/{stat}")
                continue
            x, y = np.asarray(a[feat][stat], float), np.asarray(b[feat][stat], float)
            err = float(np.abs(x.reshape(y.shape) - y).max()) if x.size == y.size else np.inf
            by_stat[stat] = max(by_stat.get(stat, 0.0), err)
            if err >= worst:
                worst, where = err, f"{feat}/{stat}"
    return {"max_abs_diff": worst, "at": where, "by_stat": by_stat, "only_in_one": only}


def same_frames(a: list[dict], b: list[dict]) -> int:
    """Rows of two read_lerobot results that differ in any field (or -1: other lengths)."""
    if len(a) != len(b):
        return -1
    return sum(set(x) != set(y) or any(not np.array_equal(x[k], y[k]) for k in x)
               for x, y in zip(a, b))


def dict_diff(a: dict, b: dict, prefix: str = "") -> list[str]:
    out = []
    for k in sorted(set(a) | set(b), key=str):
        name = f"{prefix}{k}"
        if k not in a or k not in b:
            out.append(f"{name}: only in {'ours' if k in a else 'converted'}")
        elif isinstance(a[k], dict) and isinstance(b[k], dict):
            out += dict_diff(a[k], b[k], name + ".")
        elif a[k] != b[k]:
            out.append(f"{name}: ours {a[k]!r}, converted {b[k]!r}")
    return out


def _table(root: Path, folder: str):
    import pyarrow as pa
    import pyarrow.parquet as pq

    return pa.concat_tables([pq.read_table(f) for f in sorted((root / folder).glob("*/*.parquet"))])


def compare_converted(converted: Path, v30: Path) -> dict:
    """LeRobot's conversion of our v2.1 export against our v3.0 export, file by file with
    pyarrow (data rows with the PNG bytes, column types, episode rows and their stats,
    tasks, info.json, stats.json); and whether our read_lerobot takes the conversion."""
    import pandas as pd

    from agnostos_mjx.data.lerobot import LeRobotFormatError, read_lerobot

    try:
        read_lerobot(converted)
        refused = None
    except LeRobotFormatError as err:
        refused = str(err)
    ours, conv = _table(v30, "data"), _table(converted, "data")
    rows = {}
    if ours.column_names == conv.column_names and len(ours) == len(conv):
        rows = {k: sum(x != y for x, y in zip(ours.column(k).to_pylist(),
                                              conv.column(k).to_pylist()))
                for k in ours.column_names}
    types = [f"{f.name}: ours {f.type}, converted {conv.schema.field(f.name).type}"
             for f in ours.schema if f.name in conv.column_names
             and conv.schema.field(f.name).type != f.type]
    split = lambda r: ({k: v for k, v in r.items() if not k.startswith("stats/")},  # noqa: E731
                       {k: v for k, v in r.items() if k.startswith("stats/")})
    ep_rows, ep_stats = [], 0.0
    for e, c in zip(_table(v30, "meta/episodes").to_pylist(),
                    _table(converted, "meta/episodes").to_pylist()):
        (e_plain, e_st), (c_plain, c_st) = split(e), split(c)
        ep_rows += dict_diff(e_plain, c_plain, f"episode {e['episode_index']}: ")
        ep_rows += [f"episode {e['episode_index']}: {k} only in one" for k in set(e_st) ^ set(c_st)]
        ep_stats = max([ep_stats] + [float(np.abs(np.asarray(e_st[k], float)
                                                  - np.asarray(c_st[k], float)).max())
                                     for k in set(e_st) & set(c_st)])
    tasks = [pd.read_parquet(r / "meta/tasks.parquet") for r in (v30, converted)]
    load = lambda root, name: json.loads((root / "meta" / name).read_text())  # noqa: E731
    files = lambda root: {str(p.relative_to(root)) for p in root.rglob("*")  # noqa: E731
                          if p.is_file()}
    return {
        "our_read_lerobot_refuses_it": refused,
        "data_rows": [len(ours), len(conv)],
        "data_rows_that_differ (PNG bytes, vectors, indices)": rows or "columns differ",
        "data_column_types_that_differ": types,
        "hf_schema_metadata": [b"huggingface" in (t.schema.metadata or {}) for t in (ours, conv)],
        "tasks_equal": tasks[0].equals(tasks[1]),
        "info_json_differences": dict_diff(load(v30, "info.json"),
                                           load(converted, "info.json")),
        "stats_json": stats_diff(load(v30, "stats.json"), load(converted, "stats.json")),
        "episode_rows_differences": ep_rows,
        "episode_stats_max_abs_diff": ep_stats,
        "files_only_in_ours": sorted(files(v30) - files(converted)),
        "files_only_in_converted": sorted(files(converted) - files(v30)),
    }


# ---- driver -----------------------------------------------------------------------------------
def export(work: Path) -> dict:
    base = [sys.executable, "-m", "agnostos_mjx.data.export", "--format", "lerobot",
            "--tasks", ",".join(TASKS), "--demos", str(DEMOS), "--cameras", ",".join(CAMERAS),
            "--size", str(SIZE), "--batch", "2", "--staging", str(work / "staging"), "--quiet"]
    runs = {}
    for version in ("v3.0", "v2.1"):
        cmd = [*base, "--lerobot-version", version, "--out", str(work / version)]
        stamps = {p: p.stat().st_mtime_ns for p in (work / "staging").glob("*/*.parquet")}
        t0 = time.perf_counter()
        subprocess.run(cmd, check=True, cwd=REPO, stdout=sys.stderr)
        runs[version] = {"command": shlex.join(["python", *cmd[1:]]),
                         "wall_s": round(time.perf_counter() - t0, 1),
                         "staged_demos_rewritten": sum(
                             p.stat().st_mtime_ns != s for p, s in stamps.items())}
    return runs


def run_side(python: str, script: Path, root: Path, dump: Path, mode: str, env: dict) -> dict:
    t0 = time.perf_counter()
    run = subprocess.run([*shlex.split(python), str(script), str(root), str(dump), mode],
                         env=env, capture_output=True, text=True, timeout=900)
    out = {"python_command": python, "mode": mode, "wall_s": round(time.perf_counter() - t0, 1)}
    if run.returncode:
        return {**out, "failed": True, "stderr_tail": run.stderr[-4000:]}
    side = json.loads(Path(str(dump) + ".json").read_text())
    return {**out, "failed": False, **side}


def main() -> int:
    from agnostos_mjx.infra.settings import configure_jax

    configure_jax()  # as the commands do, before JAX starts
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--lerobot-python", help="command of a Python with lerobot >= 0.4 (v3.0)")
    p.add_argument("--lerobot21-python", help="command of a Python with lerobot 0.3.3 (v2.1)")
    p.add_argument("--keep", help="keep the exports and dumps here")
    p.add_argument("--results", default=str(HERE / "results.json"))
    args = p.parse_args()
    from agnostos_mjx.data.lerobot import read_lerobot

    work = Path(args.keep or tempfile.mkdtemp(prefix="lerobot_interop_"))
    work.mkdir(parents=True, exist_ok=True)
    env = {**os.environ, "HF_HUB_OFFLINE": "1", "HF_HOME": str(work / "hf_home")}
    script = work / "side.py"
    script.write_text(side_script())
    results: dict = {"date": time.strftime("%Y-%m-%d"), "work": str(work),
                     "command": shlex.join(["python", *sys.argv]),
                     "export": {"tasks": TASKS, "demos": DEMOS, "cameras": CAMERAS,
                                "size": SIZE, "runs": export(work)}}
    ours = {v: read_lerobot(work / v) for v in ("v3.0", "v2.1")}
    results["export"]["frames"] = len(ours["v3.0"]["frames"])
    results["export"]["episodes"] = len(ours["v3.0"]["episodes"])
    results["export"]["v2.1_rows_that_differ_from_v3.0 (our reader)"] = same_frames(
        ours["v3.0"]["frames"], ours["v2.1"]["frames"])
    converted = work / "conv" / "local" / "agnostos"
    checks = []
    if args.lerobot_python:
        shutil.rmtree(work / "conv", ignore_errors=True)  # a --keep rerun converts anew
        shutil.copytree(work / "v2.1", converted)
        checks += [("LeRobotDataset reads our v3.0 export", args.lerobot_python,
                    work / "v3.0", "read", "v3.0"),
                   ("LeRobot's v2.1 -> v3.0 converter on our v2.1 export, then LeRobotDataset",
                    args.lerobot_python, converted, "convert", "v3.0")]
    if args.lerobot21_python:
        checks.append(("LeRobotDataset reads our v2.1 export", args.lerobot21_python,
                       work / "v2.1", "read", "v2.1"))
    results["checks"] = []
    for name, python, root, mode, version in checks:
        dump = work / f"{version}_{mode}.npz"
        r = {"check": name, **run_side(python, script, root, dump, mode, env)}
        if not r["failed"]:
            info, stats = r.pop("info"), r.pop("stats")
            r["dataset_codebase_version"] = info["codebase_version"]
            r.update(compare_lerobot(np.load(dump), ours[version]["frames"]))
            # v3.0: LeRobot reads our stats.json; v2.1 (0.3.3): it aggregates episodes_stats.
            r["lerobot_stats_vs_our_stats_json"] = stats_diff(stats, ours[version]["stats"])
            if mode == "convert":
                r["converted_vs_our_v3.0"] = compare_converted(converted, work / "v3.0")
        results["checks"].append(r)
    ok = bool(checks) and all(not r["failed"] and r["equal"] for r in results["checks"])
    e = results["export"]
    lines = [f"export: {', '.join(TASKS)} x {DEMOS} demos, {', '.join(CAMERAS)}, {SIZE} px: "
             f"{e['frames']} frames, {e['episodes']} episodes (v3.0 {e['runs']['v3.0']['wall_s']}"
             f" s, then v2.1 {e['runs']['v2.1']['wall_s']} s from the same staging, staged "
             f"demos rewritten: {e['runs']['v2.1']['staged_demos_rewritten']}; our reader: v2.1 "
             f"rows unlike v3.0's: {e['v2.1_rows_that_differ_from_v3.0 (our reader)']})"]
    for r in results["checks"]:
        if r["failed"]:
            lines.append(f"FAILED {r['check']} ({r['python_command']}): "
                         f"{r['stderr_tail'].strip().splitlines()[-1:]}")
            continue
        s = r["lerobot_stats_vs_our_stats_json"]
        lines.append(f"{r['check']}: lerobot {r['lerobot']} (datasets {r['datasets']}, torch "
                     f"{r['torch']}, Python {r['python']}): {r['frames']} frames, "
                     f"{r['images_compared']} images: "
                     + ("all equal" if r["equal"] else f"DIFFERENT {r['rows_that_differ']}")
                     + f"; LeRobot's stats vs our stats.json max |diff| "
                       f"{s['max_abs_diff']:.1e} ({s['at']})")
        if "converted_vs_our_v3.0" in r:
            c = r["converted_vs_our_v3.0"]
            lines.append(f"  converted vs our v3.0 export (files, pyarrow): data rows that differ "
                         f"{c['data_rows_that_differ (PNG bytes, vectors, indices)']}, column "
                         f"types that differ {c['data_column_types_that_differ']}, tasks equal "
                         f"{c['tasks_equal']}, info.json differences "
                         f"{len(c['info_json_differences'])} {c['info_json_differences'][:1]}, "
                         f"stats.json max |diff| by statistic "
                         f"{ {k: float(f'{v:.1e}') for k, v in c['stats_json']['by_stat'].items()} }"
                         f", episode rows that differ "
                         f"{len(c['episode_rows_differences'])}, episode stats max |diff| "
                         f"{c['episode_stats_max_abs_diff']:.1e}, files only in ours "
                         f"{c['files_only_in_ours']}, only in converted "
                         f"{c['files_only_in_converted']}")
            if c["our_read_lerobot_refuses_it"]:
                lines.append(f"  our read_lerobot refuses the converted dataset: "
                             f"{c['our_read_lerobot_refuses_it']}")
    lines.append(f"all equal: {ok}")
    results.update(all_equal=ok, summary=lines)
    Path(args.results).write_text(json.dumps(results, indent=1, default=str) + "\n")
    print("\n".join(lines) + f"\nresults: {args.results}; data: {work}")
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
