"""What the LLM requests of a run did: counts, retries and failures by cause, the first
message of each cause, and one record per request.

A run whose requests mostly failed must not look like a run of a weak model:
the evaluator prints `summary_lines` after the table, keeps `as_dict` in
results.json, and exits non-zero when `mostly_failed`.
"""

from __future__ import annotations

import threading
from collections import Counter
from typing import Any

from agnostos_mjx.llm.server import context_advice, context_from_error


class LLMStats:
    def __init__(self) -> None:
        self._lock = threading.Lock()
        self.records: list[dict[str, Any]] = []
        self.retries_by_cause: Counter[str] = Counter()
        self.failures_by_cause: Counter[str] = Counter()
        self.first_error: dict[str, str] = {}

    def next_number(self) -> int:
        with self._lock:
            self.records.append({})
            return len(self.records) - 1

    def finish(self, number: int, record: dict[str, Any]) -> None:
        with self._lock:
            self.records[number] = {"n": number, **record}
            if not record.get("ok") and record.get("cause"):
                self.failures_by_cause[record["cause"]] += 1

    def error_seen(self, cause: str, message: str) -> bool:
        """Remember the first message of a cause; True the first time (to log it once)."""
        with self._lock:
            if cause in self.first_error:
                return False
            self.first_error[cause] = message
            return True

    def retried(self, cause: str) -> None:
        with self._lock:
            self.retries_by_cause[cause] += 1

    @property
    def requests(self) -> int:
        return len(self.records)

    @property
    def cache_hits(self) -> int:
        return sum(bool(r.get("cached")) for r in self.records)

    @property
    def retries(self) -> int:
        return sum(self.retries_by_cause.values())

    @property
    def failures(self) -> int:
        return sum(self.failures_by_cause.values())

    def as_dict(self) -> dict[str, Any]:
        with self._lock:
            return {"requests": self.requests, "cache_hits": self.cache_hits,
                    "retries": self.retries, "failures": self.failures,
                    "retries_by_cause": dict(self.retries_by_cause),
                    "failures_by_cause": dict(self.failures_by_cause),
                    "first_error": dict(self.first_error),
                    "records": list(self.records)}


def mostly_failed(report: dict[str, Any]) -> bool:
    """More than half of the run's requests failed (an LLM run that measured nothing)."""
    return report.get("failures", 0) * 2 > report.get("requests", 0) > 0


def summary_lines(report: dict[str, Any]) -> list[str]:
    """The console summary of an `as_dict` (plus server facts when present)."""
    server = report.get("server") or {}
    where = f" ({server['software']} at {server['url']})" if server.get("url") else ""
    lines = [f"LLM{where}: {report.get('requests', 0)} requests "
             f"({report.get('cache_hits', 0)} from the cache), {report.get('retries', 0)} "
             f"retries, {report.get('failures', 0)} failed"]
    if report.get("retries_by_cause"):
        lines.append("  retries by cause: " + ", ".join(
            f"{c} {n}" for c, n in sorted(report["retries_by_cause"].items())))
    first = report.get("first_error", {})
    for cause, n in sorted(report.get("failures_by_cause", {}).items(), key=lambda kv: -kv[1]):
        lines.append(f"  failed {n} x {cause}: {first.get(cause, '')}")
        if cause == "http_400" and "context" in first.get(cause, ""):
            lines.append("  advice: " + context_advice(context_from_error(first[cause])))
    if mostly_failed(report):
        lines.append("  more than half of the LLM requests failed: the success rates above "
                     "measure the failures, not the model")
    return lines
