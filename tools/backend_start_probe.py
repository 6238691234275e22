"""Whether JAX's backend start would overlap a process's imports: a thread starts the
backend (`jax.devices()`) while the main thread runs Python, and the main thread's speed
meanwhile is compared with its speed alone.

    python tools/backend_start_probe.py

Prints one JSON line: the seconds of `import jax` and of the backend start, and the main
thread's speed during the start as a share of its speed alone (near 1: the start releases
the GIL and could run beside the imports; near 0: it holds it).  On a GPU host a process of
the main job spends about a second in the backend start
(eval/reports/main_job_h200_native/).
"""

from __future__ import annotations

import json
import threading
import time
from collections.abc import Callable


def speed_while(target: Callable[[], object]) -> float:
    """Loop iterations per second of this thread while `target` runs in another."""
    thread = threading.Thread(target=target, name="probe")
    t0, n = time.perf_counter(), 0
    thread.start()
    while thread.is_alive():
        n += 1
    return n / max(time.perf_counter() - t0, 1e-9)


def main() -> None:
    from agnostos_mjx.infra.settings import configure_jax

    configure_jax()
    alone = speed_while(lambda: time.sleep(1.0))  # a thread that holds no GIL
    t0 = time.perf_counter()
    import jax

    imported = time.perf_counter() - t0
    took: dict[str, float] = {}

    def start() -> None:
        t = time.perf_counter()
        jax.devices()
        took["start_s"] = time.perf_counter() - t

    during = speed_while(start)
    print(json.dumps({"backend": jax.default_backend(), "import_jax_s": round(imported, 3),
                      "backend_start_s": round(took["start_s"], 3),
                      "main_thread_speed_share": round(during / alone, 2)}))


if __name__ == "__main__":
    main()
