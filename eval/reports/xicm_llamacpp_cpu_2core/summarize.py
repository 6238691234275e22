"""Summarise a run folder: outcomes, LLM requests/attempts/retries from results.json."""
import collections
import json
import os
import sys
from pathlib import Path

for name in sys.argv[1:]:
    d = Path(os.environ.get("RUNS", "/work/runs")) / name
    meta = json.loads((d.parent / f"{name}.meta.json").read_text())
    res = json.loads((d / "results.json").read_text()) if (d / "results.json").exists() else None
    out = dict(meta)
    if res:
        eps = res["episodes"]
        out["outcomes"] = dict(collections.Counter(e["outcome"] for e in eps))
        plans = [p for e in eps for p in e.get("policy_info", {}).get("plans", [])]
        out["plans"] = len(plans)
        out["client_attempts"] = sum(p.get("attempts", 0) for p in plans)
        out["plans_retried"] = sum(p.get("attempts", 0) > 1 for p in plans)
        out["plan_errors"] = collections.Counter((p.get("error") or "")[:80] for p in plans if p.get("error"))
        if "llm" in res:
            llm = res["llm"]
            out["llm"] = {k: llm[k] for k in ("requests", "cache_hits", "retries", "failures", "failures_by_cause", "concurrency", "sampling_sent")}
            out["llm"]["server"] = llm["server"]["software"]
    print(json.dumps(out, default=str))
