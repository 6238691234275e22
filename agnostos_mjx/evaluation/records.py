"""episodes.jsonl: one JSON line per finished episode, the basis of --resume.

Each line is appended and fsync'd as its world finishes, so an interrupted run keeps every
finished episode and at worst tears its last line, which loading drops.
"""

from __future__ import annotations

import json
import logging
import os
import re
import shlex
from collections.abc import Sequence
from datetime import datetime
from pathlib import Path

from agnostos_mjx.infra.cli import atomic_write

log = logging.getLogger("agnostos_mjx.eval")

EPISODES_FILE = "episodes.jsonl"


def record_key(record: dict) -> tuple[str, int, int]:
    """(task, seed, episode): what identifies an episode across runs and processes."""
    return record["task"], int(record["seed"]), int(record["episode"])


def jsonl(records: Sequence[dict]) -> str:
    return "".join(json.dumps(r, sort_keys=False) + "\n" for r in records)


def load_records(path: Path) -> list[dict]:
    """Episode records of an earlier run, first of each (task, seed, episode).  A torn
    last line (the process died while appending) is dropped; other unreadable lines
    are skipped with a warning."""
    if not path.exists():
        return []
    text = path.read_text(encoding="utf-8", errors="replace")
    lines = text.split("\n")
    records: dict[tuple, dict] = {}
    for i, line in enumerate(lines, 1):
        if not line.strip():
            continue
        try:
            record = json.loads(line)
            key = record_key(record)
        except (json.JSONDecodeError, KeyError, TypeError, ValueError):
            if i == len(lines):  # no newline after it: an append cut short
                log.info("%s: ignoring the incomplete last line", path)
            else:
                log.warning("%s:%d is not a valid episode record; ignored", path, i)
            continue
        records.setdefault(key, record)
    return list(records.values())


def repair_records(path: Path) -> list[dict]:
    """`load_records`, then rewrite the file (atomically) if it held anything else, so
    appends start on a line of their own."""
    records = load_records(path)
    if path.exists() and path.read_bytes() != jsonl(records).encode("utf-8"):
        atomic_write(path, jsonl(records))
    return records


def append_records(path: Path, records: Sequence[dict]) -> None:
    """Append whole lines in one write, then fsync: a crash tears at most the last line,
    which `load_records` drops.  Creates the folder (the run has really started)."""
    data = jsonl(records).encode("utf-8")
    path.parent.mkdir(parents=True, exist_ok=True)
    fd = os.open(path, os.O_WRONLY | os.O_APPEND | os.O_CREAT, 0o644)
    try:
        view = memoryview(data)
        while view:
            view = view[os.write(fd, view):]
        os.fsync(fd)
    finally:
        os.close(fd)


def resume_command(argv: Sequence[str], out: Path) -> str:
    """The command that continues this run: the same options, then --out OUT --resume."""
    args, skip = [], False
    for a in argv:
        if skip:
            skip = False
        elif a == "--out":
            skip = True
        elif not (a.startswith("--out=") or a == "--resume"):
            args.append(a)
    return shlex.join(["python", "-m", "agnostos_mjx.eval", *args, "--out", str(out),
                       "--resume"])


def interrupted_message(out_dir: Path, argv: Sequence[str], out: Path | None = None) -> str:
    """What Ctrl-C prints: what is kept in `out_dir`, and the command that continues the
    run (whose --out is `out`, the shared folder of a multi-process run; default out_dir)."""
    kept = len(load_records(out_dir / EPISODES_FILE))
    where = (f"{kept} finished episode{'s' * (kept != 1)} saved in {out_dir / EPISODES_FILE}"
             if kept else "no episode had finished")
    return f"\ninterrupted; {where}; to continue: {resume_command(argv, out or out_dir)}"


def default_out(policy: str) -> Path:
    """A new run's folder: results/<policy>-<timestamp>."""
    tag = re.sub(r"[^A-Za-z0-9_.-]+", "_", policy.split(":")[-1]).strip("_") or "policy"
    return Path("results") / f"{tag}-{datetime.now():%Y%m%d-%H%M%S}"


def latest_run(root: Path = Path("results")) -> Path | None:
    """The most recently changed run folder (one with episodes.jsonl) under `root`."""
    runs = [p.parent for p in root.glob(f"*/{EPISODES_FILE}")]
    return max(runs, key=lambda p: (p / EPISODES_FILE).stat().st_mtime, default=None)
