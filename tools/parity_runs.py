"""The three runs whose episode records must not change in a restructuring (native backend).

    python tools/parity_runs.py OUT [--only oracle,retrieval,xicm,served]

oracle: all 41 tasks, protocol seeds; retrieval: `--selection text` on the 23 unseen tasks;
xicm: 3 unseen tasks against the loopback scripted LLM server (an answer built from the
query's first object, so the episodes move, grasp and end in several ways); served: the oracle
served over openpi's websocket protocol (`python -m agnostos_mjx.serve`, a subprocess on
loopback) and evaluated as `--policy remote` on 3 unseen tasks.  Compare two
OUT folders with `python tools/records_diff.py A/oracle B/oracle A/retrieval ...`.
"""

from __future__ import annotations

import argparse
import re
import socket
import subprocess
import sys
import time
from pathlib import Path

from agnostos_mjx import eval as ev
from agnostos_mjx.llm.testing import ScriptedLLMServer

XICM_TASKS = "lamp_on,close_microwave,put_rubbish_in_bin"
SERVED_TASKS = "lamp_on,close_microwave,put_knife_on_chopping_board"


def served_run(out: Path, common: list[str]) -> int:
    """The oracle served on a free loopback port, evaluated as a remote policy."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    server = subprocess.Popen([sys.executable, "-m", "agnostos_mjx.serve", "--policy", "oracle",
                               "--port", str(port), "--quiet"])
    try:
        for _ in range(600):  # the server imports JAX and MuJoCo before it listens
            with socket.socket() as s:
                if s.connect_ex(("127.0.0.1", port)) == 0:
                    break
            time.sleep(0.1)
        return ev.main(["--policy", "remote", "--policy-url", f"ws://127.0.0.1:{port}",
                        "--tasks", SERVED_TASKS, "--out", str(out), *common])
    finally:
        server.terminate()
        server.wait(10)


def first_object_answer(messages: list[dict]) -> str:
    """Above the query's first object, down onto it, close, lift: deterministic per prompt."""
    query = messages[-1]["content"].rsplit("]], ", 1)[-1]
    found = re.search(r"\[(\d+), (\d+), (\d+)\]", query)
    x, y, z = map(int, found.groups()) if found else (50, 50, 50)
    return (f"[[{x}, {y}, {z + 10}, 0, 36, 0, 1], [{x}, {y}, {z}, 0, 36, 0, 1], "
            f"[{x}, {y}, {z}, 0, 36, 0, 0], [{x}, {y}, {z + 12}, 0, 36, 0, 0]]")


def main(argv: list[str]) -> int:
    from agnostos_mjx.infra.settings import configure_jax

    configure_jax()  # as the commands do, before JAX starts
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    p.add_argument("out", type=Path)
    p.add_argument("--only", default="oracle,retrieval,xicm,served")
    a = p.parse_args(argv)
    common = ["--backend", "native", "--quiet"]
    runs = a.only.split(",")
    code = 0
    if "oracle" in runs:
        code |= ev.main(["--policy", "oracle", "--tasks", "all", "--out", str(a.out / "oracle"),
                         *common])
    if "retrieval" in runs:
        code |= ev.main(["--policy", "retrieval", "--selection", "text", "--tasks", "unseen",
                         "--out", str(a.out / "retrieval"), *common])
    if "xicm" in runs:
        with ScriptedLLMServer(first_object_answer) as server:
            code |= ev.main(["--policy", "xicm", "--llm-url", server.url, "--llm-model",
                             "scripted", "--selection", "text", "--tasks", XICM_TASKS,
                             "--out", str(a.out / "xicm"), *common])
    if "served" in runs:
        code |= served_run(a.out / "served", common)
    return code


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
