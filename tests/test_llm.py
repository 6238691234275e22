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
from agnostos_mjx.llm.stats import mostly_failed, summary_lines
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


@pytest.mark.parametrize("fault", ["500", "429", "reset", "cut"])
def test_transient_faults_are_retried(fault):
    with ScriptedLLMServer(echo, faults=lambda n, m: fault if n < 2 else None) as server:
        client = client_for(server)
        [result] = client.complete_batch([[{"role": "user", "content": "hi"}]])
    assert result.text == "answer to hi" and result.attempts == 3
    assert client.stats.retries == 2
    [record] = client.report()["records"]
    assert record["ok"] and len(record["causes"]) == 2 and record["attempts"] == 3


@pytest.mark.parametrize("fault, attempts, cause", [
    ("500", 4, "http_500"), ("bad_json", 1, "bad_reply"), ("no_choices", 1, "bad_reply")])
def test_persistent_faults_fail_that_request_only(fault, attempts, cause):
    bad = lambda n, m: fault if m[-1]["content"] == "bad" else None  # noqa: E731
    with ScriptedLLMServer(echo, faults=bad) as server:
        client = client_for(server)
        good, failed = client.complete_batch([[{"role": "user", "content": "ok"}],
                                              [{"role": "user", "content": "bad"}]])
    assert good.text == "answer to ok"
    assert failed.text is None and failed.error and failed.attempts == attempts
    assert failed.cause == cause and client.stats.failures_by_cause == {cause: 1}


def test_retry_after_is_honoured():
    with ScriptedLLMServer(echo, faults=lambda n, m: "429" if n == 0 else None,
                           retry_after_s=0.3) as server:
        client = client_for(server, backoff_s=0.0)
        [result] = client.complete_batch([[{"role": "user", "content": "x"}]])
    assert result.text == "answer to x" and result.latency_s >= 0.3


def test_silence_past_the_timeout_is_not_resent():
    """A server silent for longer than the timeout may still be computing: the request
    fails with cause 'timeout' and is not sent again."""
    with ScriptedLLMServer(echo, faults=lambda n, m: "timeout", hang_s=3.0) as server:
        client = client_for(server, timeout_s=0.5)
        [result] = client.complete_batch([[{"role": "user", "content": "x"}]])
        assert result.text is None and result.cause == "timeout" and result.attempts == 1
        assert len(server.requests) == 1 and client.stats.retries == 0


@pytest.mark.slow
def test_slow_streaming_server_computes_each_request_once():
    """llama.cpp with one slot, each answer taking twice the client's timeout but
    streaming keepalive bytes: the client sends one request at a time (the published
    slot count caps --llm-concurrency 8), waits, and nothing is computed twice."""
    with ScriptedLLMServer(echo, kind="llamacpp", slots=1, latency_s=5.0,
                           keepalive_s=0.1) as server:
        client = client_for(server, timeout_s=2.5, concurrency=8)
        info = client.preflight()
        prompts = [f"q{i}" for i in range(2)]
        out = client.complete_batch([[{"role": "user", "content": p}] for p in prompts])
    assert (info.kind, info.slots, client.concurrency) == ("llamacpp", 1, 1)
    assert [o.text for o in out] == [f"answer to {p}" for p in prompts]
    assert sorted(server.computed) == prompts and len(server.requests) == 2
    assert server.max_running == 1 and client.stats.retries == 0


def test_connection_refused_is_retried_and_recorded():
    with socket.socket() as s:  # a port nobody listens on
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    client = ChatClient(LLMConfig(url=f"http://127.0.0.1:{port}/v1", model="m", timeout_s=1.0,
                                  retries=2, backoff_s=0.01))
    [result] = client.complete_batch([[{"role": "user", "content": "x"}]])
    assert result.text is None and result.cause == "connection" and result.attempts == 3
    assert client.stats.retries_by_cause == {"connection": 2}
    report = client.report()
    assert report["failures_by_cause"] == {"connection": 1}
    assert "Connection" in report["first_error"]["connection"]
    lines = summary_lines(report)
    assert "1 requests" in lines[0] and "2 retries" in lines[0] and "1 failed" in lines[0]
    assert any("connection" in line and "Connection" in line for line in lines[1:])
    assert mostly_failed(report)


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


@pytest.mark.parametrize("form", ["{root}", "{root}/", "{root}/v1/", "{root}/v1/chat/completions",
                                  "{root}/v1/models"])
def test_preflight_fixes_the_usual_url_forms(form):
    with ScriptedLLMServer(echo, kind="vllm") as server:
        root = server.url[:-len("/v1")]
        client = client_for(server, url=form.format(root=root))
        info = client.preflight()
        [result] = client.complete_batch([[{"role": "user", "content": "x"}]])
    assert client.url == server.url and info.kind == "vllm"
    assert result.text == "answer to x" and len(server.probes) == 1
    assert bool(info.notes) == (form.format(root="") not in ("/v1/",))


@pytest.mark.parametrize("kind, field, used", [
    ("vllm", "repetition_penalty", 1.05), ("llamacpp", "repeat_penalty", 1.05),
    ("llama-cpp-python", "repeat_penalty", 1.05), ("openai", None, 1.0)])
def test_repetition_penalty_reaches_each_kind_of_server(kind, field, used):
    with ScriptedLLMServer(echo, kind=kind) as server:
        client = client_for(server)
        client.preflight()
        client.complete_batch([[{"role": "user", "content": "x"}]])
    [sent] = server.requests
    names = {"repetition_penalty", "repeat_penalty", "frequency_penalty"} & set(sent)
    assert names == ({field} if field else set())
    assert server.penalty_used == [used]  # what the server sampled with
    assert client.report()["sampling_sent"] == {k: v for k, v in sent.items()
                                                if k not in ("model", "messages", "stream")}


def test_server_kind_override_and_concurrency_defaults():
    with ScriptedLLMServer(echo, kind="llamacpp", slots=4) as server:
        client = client_for(server, server_kind="vllm", concurrency=None)
        client.preflight()
        client.complete_batch([[{"role": "user", "content": "x"}]])
        assert client.concurrency == 4  # the published slots
    assert "repetition_penalty" in server.requests[0]
    assert server.penalty_used == [1.1]  # llama.cpp ignored vLLM's name: its default
    for kind, expected in (("vllm", 64), ("openai", 8), ("llama-cpp-python", 1)):
        with ScriptedLLMServer(echo, kind=kind) as server:
            client = client_for(server, concurrency=None)
            client.preflight()
            assert client.concurrency == expected, kind
    with ScriptedLLMServer(echo, kind="openai") as server:
        client = client_for(server, concurrency=3)
        client.preflight()
        assert client.concurrency == 3  # nothing published: the flag


def test_prompt_tokens_from_the_server_or_an_estimate():
    msgs = [{"role": "user", "content": "x" * 400}]
    with ScriptedLLMServer(echo, kind="vllm", context=2048) as server:
        client = client_for(server)
        info = client.preflight()
        assert info.context == 2048 and client.context_length == 2048
        assert client.count_tokens(msgs) == (108, "the server's /tokenize")
    with ScriptedLLMServer(echo, kind="openai") as server:
        client = client_for(server)
        assert client.preflight().context is None
        tokens, how = client.count_tokens(msgs)
        assert tokens >= 400 // 3 and "estimate" in how


@pytest.mark.parametrize("kind", ["openai", "llama-cpp-python"])
def test_context_error_is_not_retried_and_explained(kind):
    """A 400 is final.  llama-cpp-python answers an over-long streamed prompt with an
    empty stream: the client asks once more without streaming and gets the 400."""
    with ScriptedLLMServer(echo, kind=kind, context=100) as server:
        client = client_for(server)
        client.preflight()  # a 1-token test fits; the context is not published
        [result] = client.complete_batch([[{"role": "user", "content": "x" * 1000}]])
    causes = ["empty_stream", "http_400"] if kind == "llama-cpp-python" else ["http_400"]
    assert client.report()["records"][0]["causes"] == causes
    assert result.cause == "http_400" and result.attempts == len(server.requests) == len(causes)
    assert [r.get("stream") for r in server.requests] == [True, False][:len(causes)]
    assert server.computed == []
    lines = summary_lines(client.report())
    failed = next(line for line in lines if "failed 1 x http_400" in line)
    assert "maximum context length is 100 tokens" in failed
    assert "--num-demos" in lines[-2] and "context is 100 tokens" in lines[-2]


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
        code = ev.main(["--llm-url", server.url[:-len("/v1")], "--llm-model", "scripted",
                        "--tasks", "lamp_on",
                        "--seeds", "0", "--episodes", "2", "--batch", "2", "--backend",
                        "native", "--quiet", "--selection", "random", "--num-demos", "3",
                        "--memory", str(memory_file), "--out", str(tmp_path / "run")])
        requests = len(server.requests)
    assert code == 0
    stdout = capsys.readouterr().out.splitlines()
    assert stdout[0].startswith("agnostos_mjx.eval: policy xicm (an LLM is configured")
    assert stdout[-1].endswith(f"{requests} requests (0 from the cache), 0 retries, 0 failed")
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


def test_bad_answers_and_dead_requests_end_episodes_with_reasons(memory_file, tmp_path, capsys):
    from agnostos_mjx import eval as ev

    answers = {"garbage": lambda m: "I would rather not.", "error": None}
    for reason, responder in answers.items():
        faults = (lambda n, m: "500") if responder is None else None
        with ScriptedLLMServer(responder or echo, faults=faults) as server:
            out = tmp_path / reason
            code = ev.main(run_args(server.url, memory_file, out, "--num-demos", "2",
                                    "--policy-arg", "retries=1"))
        records = [json.loads(line) for line in (out / "episodes.jsonl").open()]
        expected = "bad_llm_output" if reason == "garbage" else "llm_error"
        assert [r["outcome"] for r in records] == [expected] * 2
        # Every request failed: the summary says why and the exit code is not 0.
        assert code == (3 if reason == "error" else 0)
        if reason == "error":
            stdout = capsys.readouterr().out
            assert "2 retries, 2 failed" in stdout and "failed 2 x http_500: HTTP 500" in stdout
            llm = json.loads((out / "results.json").read_text())["llm"]
            assert llm["failures_by_cause"] == {"http_500": 2} and len(llm["records"]) == 2
            assert records[0]["policy_info"]["plans"][0]["cause"] == "http_500"


def run_args(url: str, memory_file: Path, out: Path, *extra: str) -> list[str]:
    return ["--llm-url", url, "--llm-model", "scripted", "--tasks", "lamp_on", "--seeds", "0",
            "--episodes", "2", "--batch", "2", "--backend", "native", "--quiet",
            "--selection", "random", "--memory", str(memory_file), "--out", str(out), *extra]


@pytest.mark.parametrize("case", ["wrong path", "wrong model", "wrong key", "dead"])
def test_bad_endpoints_are_one_line_and_exit_2_before_any_episode(case, memory_file, tmp_path,
                                                                  capsys, monkeypatch):
    from agnostos_mjx import eval as ev

    monkeypatch.setenv("AGNOSTOS_LLM_API_KEY", "wrong" if case == "wrong key" else "secret")
    with ScriptedLLMServer(echo, kind="vllm", api_key="secret") as server:
        root = server.url[:-len("/v1")]
        url = {"wrong path": root + "/api/v2", "dead": "http://127.0.0.1:9/v1"}.get(case,
                                                                                 server.url)
        args = run_args(url, memory_file, tmp_path / "run", "--num-demos", "2")
        if case == "wrong model":
            args[args.index("scripted")] = "other"
        code = ev.main(args)
        sent = len(server.requests)
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and sent == 0 and not (tmp_path / "run" / "episodes.jsonl").exists()
    assert len(err) == 1 and err[0].startswith("error: "), err
    assert {"wrong path": "HTTP 404", "wrong model": "does not serve model 'other'",
            "wrong key": "rejected the API key", "dead": "unreachable"}[case] in err[0]


def test_small_published_context_is_an_error_before_the_run(memory_file, tmp_path, capsys):
    from agnostos_mjx import eval as ev

    with ScriptedLLMServer(echo, kind="llamacpp", context=450) as server:
        code = ev.main(run_args(server.url, memory_file, tmp_path / "run", "--num-demos", "3"))
        sent = len(server.requests)
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and sent == 0 and len(err) == 1
    assert "context is 450 tokens" in err[0] and "--num-demos" in err[0]


def test_small_unpublished_context_is_printed_and_exits_non_zero(memory_file, tmp_path, capsys):
    """llama-cpp-python publishes no context length: every request gets HTTP 400; the
    cause and advice are printed after the table and the exit code is 3."""
    from agnostos_mjx import eval as ev

    with ScriptedLLMServer(echo, kind="llama-cpp-python", context=450) as server:
        code = ev.main(run_args(server.url, memory_file, tmp_path / "run", "--num-demos", "3"))
        sent = len(server.requests)
    out = capsys.readouterr().out
    assert code == 3 and sent == 4  # per episode: the empty stream, then unstreamed 400
    assert "failed 2 x http_400" in out and "maximum context length is 450 tokens" in out
    assert "--num-demos" in out and "more than half of the LLM requests failed" in out
    llm = json.loads((tmp_path / "run" / "results.json").read_text())["llm"]
    assert llm["server"]["software"] == "llama-cpp-python" and llm["concurrency"] == 1
    assert llm["sampling_sent"]["repeat_penalty"] == 1.05
    assert [r["causes"] for r in llm["records"]] == [["empty_stream", "http_400"]] * 2


def test_llm_flags_are_documented(capsys):
    from agnostos_mjx import eval as ev
    from agnostos_mjx.evaluation.config import parse_config, resolve_policy

    with pytest.raises(SystemExit):
        ev.main(["--help"])
    out = capsys.readouterr().out
    for flag in ("--llm-timeout", "--llm-concurrency", "--llm-server-kind"):
        assert flag in out
    cfg = parse_config(["--llm-timeout", "30", "--llm-server-kind", "llamacpp"])
    _, kwargs, _ = resolve_policy(cfg.with_options(policy="xicm"))
    assert (kwargs["timeout_s"], kwargs["server_kind"], kwargs["concurrency"]) == (
        30.0, "llamacpp", None)


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
    """A press_the_button server script for lamp_on and lamp_off that notes, as each
    request arrives, how many requests of the other task are unanswered; with `hold` it
    answers a request only once the other task has sent one (which only overlapping tasks
    can make happen, whichever task asks first)."""
    arrived = {"on": threading.Event(), "off": threading.Event()}
    lock = threading.Lock()
    state = {"in_flight": {"on": 0, "off": 0}, "seen_in_flight": [], "held": []}

    def respond(msgs):
        task = "on" if "turn on" in msgs[-1]["content"] else "off"
        other = "off" if task == "on" else "on"
        with lock:
            state["seen_in_flight"].append(state["in_flight"][other])
            state["in_flight"][task] += 1
        arrived[task].set()
        try:
            if hold:  # a safety net below the client's 60 s timeout, not a timing assumption
                state["held"].append(arrived[other].wait(50))
            return press_the_button(msgs)
        finally:
            with lock:
                state["in_flight"][task] -= 1

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
        assert len(state["seen_in_flight"]) >= 2, "a task sent no request"
        if overlap == 1:  # one task starts after the other's last answer
            assert state["held"] == [] and set(state["seen_in_flight"]) == {0}
        else:  # every held request was released by one of the other task
            assert state["held"] and all(state["held"])
            assert max(state["seen_in_flight"]) > 0
    assert runs[1] == runs[2]
