"""The selection's one program in a fresh process: its compile, its time per call, its
scores for fixed queries (saved, to compare compiles), and whether a query's scores depend
on its place in the call.

    AGNOSTOS_JAX_CACHE=<empty dir> [XLA_FLAGS=...] python tools/selection_compile.py LABEL OUT

Run it twice from empty caches and compare the saved scores (numpy) to see whether two
compiles agree; eval/reports/main_job_h100_native has a GPU's figures.
"""

from __future__ import annotations

import json
import sys
import time
from pathlib import Path

import numpy as np

from agnostos_mjx.infra.settings import configure_jax


def main(label: str, out: Path) -> dict:
    configure_jax()
    from agnostos_mjx.policies.retrieval import RetrievalPolicy

    t0 = time.perf_counter()
    selector = RetrievalPolicy().selector
    chunk = selector.pipeline.chunk_size
    rng = np.random.default_rng(0)
    frames = rng.integers(0, 255, (chunk, 128, 128, 3), np.uint8)
    texts = ["press the button", "open the drawer", "put the knife on the board"]
    rows = [(frames[i], texts[i % 3]) for i in range(chunk)]
    t1 = time.perf_counter()
    first = np.stack(selector._similarities(rows))
    t2 = time.perf_counter()
    for _ in range(10):
        again = np.stack(selector._similarities(rows))
    t3 = time.perf_counter()
    last = chunk - 1
    moved = [rows[last], *rows[1:last], rows[0]]  # the first and last queries swap places
    swapped = np.stack(selector._similarities(moved))
    out.mkdir(parents=True, exist_ok=True)
    np.save(out / f"scores_{label}.npy", first)
    return {"label": label, "rows": chunk, "load_s": round(t1 - t0, 2),
            "first_call_s": round(t2 - t1, 2), "per_call_ms": round((t3 - t2) * 100, 1),
            "repeat_identical": bool((again == first).all()),
            "place_max_diff": float(np.abs(swapped[last] - first[0]).max())}


if __name__ == "__main__":
    if len(sys.argv) != 3:
        sys.exit(__doc__)
    print(json.dumps(main(sys.argv[1], Path(sys.argv[2]))))
