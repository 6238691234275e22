"""LLM request throughput against the scripted loopback server:
``python -m agnostos_mjx.bench.llm``.

Measures how long `--requests` chat completions take with `--latency` s of
server latency at the client's concurrency, against the sequential time the
original's one-request-at-a-time loop would need (requests x latency).  A
benchmark, not a test: nothing asserts on the numbers.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from collections.abc import Sequence

from agnostos_mjx.infra.cli import HelpFormatter
from agnostos_mjx.llm.client import ChatClient, LLMConfig
from agnostos_mjx.llm.testing import ScriptedLLMServer


def run(requests: int, latency_s: float, concurrency: int) -> dict:
    answer = "[[57, 49, 87, 0, 39, 0, 1]]"
    with ScriptedLLMServer(lambda m: answer, latency_s=latency_s) as server:
        client = ChatClient(LLMConfig(url=server.url, model="scripted", concurrency=concurrency,
                                      timeout_s=30.0))
        batch = [[{"role": "user", "content": f"request {i}"}] for i in range(requests)]
        t0 = time.perf_counter()
        out = client.complete_batch(batch)
        wall = time.perf_counter() - t0
        client.close()
    ok = sum(c.text == answer for c in out)
    sequential = requests * latency_s
    return {"requests": requests, "ok": ok, "latency_s": latency_s, "concurrency": concurrency,
            "wall_s": round(wall, 3), "sequential_s": round(sequential, 1),
            "speedup": round(sequential / wall, 1), "requests_per_s": round(requests / wall, 1)}


def main(argv: Sequence[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m agnostos_mjx.bench.llm",
                                formatter_class=HelpFormatter, description=__doc__.split("\n\n")[0])
    p.add_argument("--requests", type=int, default=1725,
                   help="requests to send (1,725 = 23 tasks x 75 episodes)")
    p.add_argument("--latency", type=float, default=0.2, help="server latency per request, s")
    p.add_argument("--concurrency", type=int, default=64, help="client requests in flight")
    p.add_argument("--quick", action="store_true", help="200 requests (a few seconds)")
    a = p.parse_args(argv)
    result = run(200 if a.quick else a.requests, a.latency, a.concurrency)
    print(json.dumps(result))
    print(f"{result['ok']}/{result['requests']} requests in {result['wall_s']:.1f} s at "
          f"concurrency {result['concurrency']} ({result['latency_s'] * 1000:.0f} ms latency); "
          f"sequential would take {result['sequential_s']:.0f} s: {result['speedup']:.0f}x")
    return 0 if result["ok"] == result["requests"] else 1


if __name__ == "__main__":
    sys.exit(main())
