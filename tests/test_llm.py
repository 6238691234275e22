"""X-ICM's prompt, the answer parser, the LLM client against a real loopback
HTTP server with scripted answers and injected faults, and an end-to-end
evaluation through that server."""

from __future__ import annotations

import json
import random
import re
import socket
import threading
from pathlib import Path

import numpy as np
import pytest

from agnostos_mjx.llm.client import ChatClient, LLMConfig, LLMConfigError
from agnostos_mjx.llm.testing import ScriptedLLMServer
from agnostos_mjx.xicm.prompt import SYSTEM_PROMPT, messages, parse_actions

GOLDEN = Path(__file__).parent / "golden"
DEMO = ("['instruction': close the red jar, {'lid': [52, 38, 17], 'jar': [47, 61, 16]}]>"
        "[[52, 38, 24, 0, 39, 0, 1], [52, 38, 18, 0, 39, 0, 0]], ")
QUERY = "['instruction': turn on the light, {'button': [60, 40, 15]}]>"


# ---- prompt ------------------------------------------------------------------------------
def test_prompt_matches_golden_files():
    msgs = messages([DEMO, DEMO.replace("red", "blue")], QUERY)
    assert [m["role"] for m in msgs] == ["system", "user"]
    assert msgs[0]["content"] == (GOLDEN / "system_prompt.txt").read_text().rstrip("\n")
    assert msgs[1]["content"] == (GOLDEN / "user_prompt.txt").read_text().rstrip("\n")
    assert "\n" not in msgs[1]["content"]  # one line, as the original
    assert SYSTEM_PROMPT.startswith("You are a Franka Panda robot")


# ---- parsing -----------------------------------------------------------------------------
@pytest.mark.parametrize("answer, expected", [
    ("[[52, 38, 24, 0, 39, 0, 1], [52, 38, 18, 0, 39, 0, 0]]", 2),
    ("Sure! Here is the plan:\n[[1, 2, 3, 4, 5, 6, 1]]\nHope it helps.", 1),  # chatty
    ("[[1, 2, 3, 4, 5, 6, 1], [1, 2, 3, 4, 5, 6, 0], [7, 8, 9", 2),  # truncated
    ("[[1.5, 2, 3, 4, 5, 6, 1], [1, 2, 3, 4, 5, 6, 0]]", 1),  # one float group
    ("[[100, 2, 3, 4, 5, 6, 1], [1, 2, 3, 4, 72, 6, 1], [1, 2, 3, 4, 5, 6, 2]]", 0),  # ranges
    ("[[1, 2, 3, 4, 5, 6]]", 0),  # six values
    ("I cannot do that.", 0),
    ("", 0),
])
def test_parser_keeps_valid_groups(answer, expected):
    plan = parse_actions(answer)
    assert plan.actions.shape == (expected, 7) and plan.actions.dtype == np.int32


def test_parser_truncates_to_26_and_survives_fuzzing():
    many = "[" + ", ".join(["[1, 2, 3, 4, 5, 6, 1]"] * 40) + "]"
    assert len(parse_actions(many).actions) == 26
    rng = random.Random(0)
    alphabet = "[]0123456789,- .abcxyz\n\t{}'\"e+"
    for _ in range(3000):
        text = "".join(rng.choice(alphabet) for _ in range(rng.randint(0, 120)))
        plan = parse_actions(text)
        assert plan.actions.ndim == 2 and plan.actions.shape[1] == 7
        assert ((plan.actions[:, :3] >= 0) & (plan.actions[:, :3] <= 99)).all()
    for junk in (None, 42, b"[[1,2,3,4,5,6,1]]", ["x"]):
        assert parse_actions(junk).actions.shape == (0, 7)


# ---- client ------------------------------------------------------------------------------
def client_for(server: ScriptedLLMServer, **kwargs) -> ChatClient:
    config = dict(url=server.url, model="scripted", timeout_s=1.0, retries=3, backoff_s=0.01,
                  concurrency=8)
    config.update(kwargs)
    return ChatClient(LLMConfig(**config))


def echo(msgs):
    return "answer to " + msgs[-1]["content"]


@pytest.mark.parametrize("fault", ["500", "429", "timeout"])
def test_transient_faults_are_retried(fault):
    with ScriptedLLMServer(echo, faults=lambda n, m: fault if n < 2 else None,
                           hang_s=1.5) as server:
        client = client_for(server)
        [result] = client.complete_batch([[{"role": "user", "content": "hi"}]])
    assert result.text == "answer to hi" and result.attempts == 3
    assert client.stats["retries"] == 2


@pytest.mark.parametrize("fault, attempts", [("500", 4), ("bad_json", 1), ("no_choices", 1)])
def test_persistent_faults_fail_that_request_only(fault, attempts):
    bad = lambda n, m: fault if m[-1]["content"] == "bad" else None  # noqa: E731
    with ScriptedLLMServer(echo, faults=bad) as server:
        client = client_for(server)
        good, failed = client.complete_batch([[{"role": "user", "content": "ok"}],
                                              [{"role": "user", "content": "bad"}]])
    assert good.text == "answer to ok"
    assert failed.text is None and failed.error and failed.attempts == attempts


def test_retry_after_is_honoured():
    with ScriptedLLMServer(echo, faults=lambda n, m: "429" if n == 0 else None,
                           retry_after_s=0.3) as server:
        client = client_for(server, backoff_s=0.0)
        [result] = client.complete_batch([[{"role": "user", "content": "x"}]])
    assert result.text == "answer to x" and result.latency_s >= 0.3


def test_preflight_errors_are_clear():
    with ScriptedLLMServer(echo, api_key="secret") as server:
        client_for(server, api_key="secret").preflight()
        with pytest.raises(LLMConfigError, match="rejected the API key"):
            client_for(server, api_key="wrong").preflight()
        with pytest.raises(LLMConfigError, match="does not serve model 'other'"):
            client_for(server, model="other", api_key="secret").preflight()
    with socket.socket() as s:  # a port nobody listens on
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    dead = ChatClient(LLMConfig(url=f"http://127.0.0.1:{port}/v1", model="m", timeout_s=1.0))
    with pytest.raises(LLMConfigError, match="unreachable"):
        dead.preflight()
    with pytest.raises(LLMConfigError, match="no model"):
        LLMConfig.from_env("http://localhost:1/v1", None)


def test_cache_replays_without_the_server(tmp_path):
    with ScriptedLLMServer(echo) as server:
        client = client_for(server, cache_dir=str(tmp_path))
        first = client.complete_batch([[{"role": "user", "content": f"q{i}"}] for i in range(5)])
        assert len(server.requests) == 5
        again = client_for(server, cache_dir=str(tmp_path)).complete_batch(
            [[{"role": "user", "content": f"q{i}"}] for i in range(5)])
        assert len(server.requests) == 5  # all from the cache
    assert [a.text for a in again] == [f.text for f in first] and all(a.cached for a in again)


def test_concurrency_overlaps_latency():
    """Requests are in flight together: the server answers only in groups of 8 that are
    all waiting at once (a barrier, so load cannot break it; sequential requests would
    break the barrier and fail)."""
    barrier = threading.Barrier(8, timeout=50)

    def together(msgs):
        barrier.wait()
        return echo(msgs)

    with ScriptedLLMServer(together) as server:
        client = client_for(server, concurrency=32, timeout_s=60.0, retries=0)
        out = client.complete_batch([[{"role": "user", "content": str(i)}] for i in range(64)])
    assert all(o.text == f"answer to {i}" for i, o in enumerate(out))


# ---- end to end --------------------------------------------------------------------------
def press_the_button(msgs) -> str:
    """A scripted 'LLM' that reads the query's button voxel and answers chatty."""
    query = msgs[-1]["content"].rsplit("]], ", 1)[-1]
    x, y, z = map(int, re.search(r"'button': \[(\d+), (\d+), (\d+)\]", query).groups())
    return f"Here you go: [[{x}, {y}, {z + 8}, 0, 36, 0, 0], [{x}, {y}, {z + 1}, 0, 36, 0, 0]]"


@pytest.fixture(scope="module")
def memory_file(bank_dir, tmp_path_factory) -> Path:
    from agnostos_mjx.data import DemoBank
    from agnostos_mjx.xicm.memory import DemoMemory

    path = tmp_path_factory.mktemp("memory") / "memory.npz"
    DemoMemory.from_bank(DemoBank(bank_dir)).save(path)
    return path


def test_xicm_end_to_end_through_the_server(memory_file, tmp_path, capsys):
    from agnostos_mjx import eval as ev

    with ScriptedLLMServer(press_the_button, latency_s=0.05) as server:
        code = ev.main(["--llm-url", server.url, "--llm-model", "scripted", "--tasks", "lamp_on",
                        "--seeds", "0", "--episodes", "2", "--batch", "2", "--backend",
                        "native", "--quiet", "--selection", "random", "--num-demos", "3",
                        "--memory", str(memory_file), "--out", str(tmp_path / "run")])
        requests = len(server.requests)
    assert code == 0
    assert capsys.readouterr().out.splitlines()[0].startswith(
        "agnostos_mjx.eval: policy xicm (an LLM is configured")
    records = [json.loads(line) for line in (tmp_path / "run" / "episodes.jsonl").open()]
    assert len(records) == 2 and requests >= 2
    for r in records:
        assert r["success"], r["outcome"]
        plan = r["policy_info"]["plans"][0]
        assert plan["prompt"].count(">[[") == 3 and plan["prompt"].endswith("]>")
        assert plan["parsed"]["actions"] and plan["response"].startswith("Here you go")
    # Rerunning against the same cache asks the server nothing.
    with ScriptedLLMServer(lambda m: "unused") as server:
        assert ev.main(["--llm-url", server.url, "--llm-model", "scripted", "--tasks",
                        "lamp_on", "--seeds", "0", "--episodes", "2", "--batch", "2",
                        "--backend", "native", "--quiet", "--selection", "random",
                        "--num-demos", "3", "--memory", str(memory_file), "--llm-cache",
                        str(tmp_path / "run" / "llm_cache"), "--out",
                        str(tmp_path / "rerun")]) == 0
        assert len(server.requests) == 0


def test_bad_answers_and_dead_requests_end_episodes_with_reasons(memory_file, tmp_path):
    from agnostos_mjx import eval as ev

    answers = {"garbage": lambda m: "I would rather not.", "error": None}
    for reason, responder in answers.items():
        faults = (lambda n, m: "500") if responder is None else None
        with ScriptedLLMServer(responder or echo, faults=faults) as server:
            out = tmp_path / reason
            assert ev.main(["--llm-url", server.url, "--llm-model", "scripted", "--tasks",
                            "lamp_on", "--seeds", "0", "--episodes", "2", "--batch", "2",
                            "--backend", "native", "--quiet", "--selection", "random",
                            "--num-demos", "2", "--memory", str(memory_file), "--out", str(out),
                            "--policy-arg", "retries=1"]) == 0
        records = [json.loads(line) for line in (out / "episodes.jsonl").open()]
        expected = "bad_llm_output" if reason == "garbage" else "llm_error"
        assert [r["outcome"] for r in records] == [expected] * 2


def test_vllm_engine_without_vllm_is_a_clear_error(monkeypatch):
    import builtins

    real_import = builtins.__import__

    def no_vllm(name, *args, **kwargs):
        if name == "vllm":
            raise ImportError("no vllm")
        return real_import(name, *args, **kwargs)

    monkeypatch.setattr(builtins, "__import__", no_vllm)
    from agnostos_mjx.llm.vllm_engine import VLLMEngine

    with pytest.raises(LLMConfigError, match="needs vLLM"):
        VLLMEngine(LLMConfig(url="vllm:", model="Qwen/Qwen2.5-7B-Instruct"))


def _overlap_probe(hold: bool):
    """A press_the_button server script that notes, as each lamp_off request arrives, how
    many lamp_on requests are unanswered; with `hold` it answers lamp_on only once a
    lamp_off request has arrived (which only overlapping tasks can make happen)."""
    other_arrived, lock = threading.Event(), threading.Lock()
    state = {"on_in_flight": 0, "seen_in_flight": [], "held": []}

    def respond(msgs):
        if "turn on" not in msgs[-1]["content"]:
            with lock:
                state["seen_in_flight"].append(state["on_in_flight"])
            other_arrived.set()
            return press_the_button(msgs)
        with lock:
            state["on_in_flight"] += 1
        try:
            if hold:  # a safety net below the client's 60 s timeout, not a timing assumption
                state["held"].append(other_arrived.wait(50))
            return press_the_button(msgs)
        finally:
            with lock:
                state["on_in_flight"] -= 1

    return respond, state


def test_tasks_overlap_while_their_requests_wait(memory_file, tmp_path):
    """With --overlap-tasks 2 the second task simulates and sends its requests while the
    first task's requests are in flight; the episodes are the same as one task at a time.
    Decided by the order of events on the server, not by wall-clock time."""
    from agnostos_mjx import eval as ev

    runs = {}
    for overlap in (1, 2):
        respond, state = _overlap_probe(hold=overlap == 2)
        with ScriptedLLMServer(respond) as server:
            out = tmp_path / f"overlap{overlap}"
            assert ev.main(["--llm-url", server.url, "--llm-model", "scripted", "--tasks",
                            "lamp_on,lamp_off", "--seeds", "0", "--episodes", "2", "--batch",
                            "2", "--backend", "native", "--quiet", "--selection", "random",
                            "--num-demos", "2", "--memory", str(memory_file), "--out", str(out),
                            "--overlap-tasks", str(overlap)]) == 0
        records = [json.loads(line) for line in (out / "episodes.jsonl").open()]
        for r in records:
            r.pop("wall_s")
        runs[overlap] = sorted(records, key=lambda r: (r["task"], r["episode"]))
        assert state["seen_in_flight"], "lamp_off sent no request"
        if overlap == 1:  # lamp_off starts after lamp_on's last answer
            assert state["held"] == [] and set(state["seen_in_flight"]) == {0}
        else:  # every held lamp_on request was released by a lamp_off request
            assert state["held"] and all(state["held"])
            assert max(state["seen_in_flight"]) > 0
    assert runs[1] == runs[2]
