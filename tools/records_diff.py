"""Compare the episode records of two runs field by field, timing aside.

    python tools/records_diff.py RUN_A RUN_B [RUN_A2 RUN_B2 ...]

Each RUN is a run folder (its episodes.jsonl, or episodes.jsonl.gz as reports keep them) or a
jsonl file.  Episodes are matched by
(task, seed, episode); every field except timing (`wall_s`, `batch_size`-independent
timing keys) that both records have must be equal; a field only one side has (a run of
an older version lacks the newer fields) is named, not counted.  Prints per pair: episodes, identical, differing (first few
with the fields that differ), missing on either side.  Exit 1 when any pair differs.
"""

from __future__ import annotations

import gzip
import json
import sys
from pathlib import Path

TIMING = {"wall_s"}


def _strip(value):
    """Drop timing keys at any depth (LLM reports carry latencies)."""
    if isinstance(value, dict):
        return {k: _strip(v) for k, v in value.items()
                if k not in TIMING and not k.endswith("_s") and "latency" not in k}
    if isinstance(value, list):
        return [_strip(v) for v in value]
    return value


def load(path: Path) -> dict[tuple, dict]:
    file = path / "episodes.jsonl" if path.is_dir() else path
    if not file.exists() and file.with_suffix(".jsonl.gz").exists():
        file = file.with_suffix(".jsonl.gz")
    text = gzip.decompress(file.read_bytes()).decode() if file.suffix == ".gz" else file.read_text()
    out = {}
    for line in text.splitlines():
        if line.strip():
            r = json.loads(line)
            out[(r["task"], r["seed"], r["episode"])] = _strip(r)
    return out


def compare(a: Path, b: Path) -> bool:
    ra, rb = load(a), load(b)
    common = sorted(set(ra) & set(rb))
    one_sided = set()
    for k in common:
        one_sided |= set(ra[k]) ^ set(rb[k])
    shared = lambda r: {f: v for f, v in r.items() if f not in one_sided}  # noqa: E731
    differ = [k for k in common if shared(ra[k]) != shared(rb[k])]
    print(f"{a} vs {b}: {len(common)} episodes in both, {len(common) - len(differ)} identical, "
          f"{len(differ)} differ, {len(set(ra) - set(rb))} only in A, "
          f"{len(set(rb) - set(ra))} only in B"
          + (f" (fields on one side only: {', '.join(sorted(one_sided))})" if one_sided else ""))
    for k in differ[:5]:
        fields = sorted(f for f in set(ra[k]) | set(rb[k]) if ra[k].get(f) != rb[k].get(f))
        print(f"  {k}: {fields}")
    return not differ and set(ra) == set(rb)


def main(argv: list[str]) -> int:
    if len(argv) < 2 or len(argv) % 2:
        print(__doc__)
        return 2
    ok = all([compare(Path(a), Path(b)) for a, b in zip(argv[::2], argv[1::2])])
    return 0 if ok else 1


if __name__ == "__main__":
    try:
        sys.exit(main(sys.argv[1:]))
    except BrokenPipeError:  # `| head`: the reader has what it wanted
        sys.stderr.close()
        sys.exit(0)
