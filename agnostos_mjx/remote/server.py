"""The reference policy server: any of our policies over openpi's websocket protocol, or
over HTTP with json_numpy bodies (OpenVLA's deploy.py protocol, `JsonNumpyServer`).

Our policies are written against the evaluator's ``Episodes`` runner and ``EnvState``
(the oracle reads the scene the episode started from, retrieval the current object
poses).  A server sees only what a request carries, so the reference server asks for the
``sim_state`` source (preset ``sim``, announced in its metadata as ``agnostos_preset``):
the world's sensor data now and at reset, its grasp state, joint and mocap positions and
colours, task, variation and episode seed.  From it each connection rebuilds a one-world
``EnvState`` (the *mirror*) and runs its own copy of the policy on it; the policy is reset
when an episode starts (``key_actions == 0``, or another task or episode seed).  A policy
that declares an ObservationSpec is shown the mirror rendered.  The answer is a chunk of
one key action ``[x, y, z, qx, qy, qz, qw, open]`` (float32, world frame), or an empty
chunk when the policy has nothing to execute.

The mirror holds everything the built-in policies read, so the served oracle's episodes
equal the in-process oracle's (tests/test_serve.py).  It is privileged information: a
learned policy served for evaluation would take the rendered cameras instead.

Both servers take `faults` (tests) and a replacement for the policy's sessions
(`session=` / `infer=`: anything that maps a request to an answer), so tests can serve
answers in other layouts (X-ICM's Euler rows, OpenVLA's deltas) from the same oracle.
"""

from __future__ import annotations

import asyncio
import collections
import concurrent.futures
import functools
import http
import http.server
import logging
import threading
import traceback
from collections.abc import Callable
from typing import Any

import numpy as np
from websockets.asyncio.server import Server, ServerConnection, serve
from websockets.exceptions import ConnectionClosed
from websockets.frames import CloseCode

from agnostos_mjx.policies.base import Policy, Round
from agnostos_mjx.remote import json_wire, wire

log = logging.getLogger("agnostos_mjx.serve")
# Faults for tests: given the decoded request, None or "drop" (close without answering),
# "stall" (answer after `stall_s`), "garbage" (bytes that are not msgpack / JSON),
# "no_actions" (a map without "actions") or "error" (raise: over websockets the traceback
# as text, then close; over HTTP deploy.py's answer, the JSON string "error"); over HTTP
# also "http_error" (status 500).
Faults = Callable[[dict], str | None]


@functools.cache
def runner_for(task_name: str):
    """One Episodes runner per task (scene, expert, renderer), built on first use."""
    from agnostos_mjx.runtime.env import Episodes
    from agnostos_mjx.tasks import get_task

    return Episodes(get_task(task_name), "native")


def mirror_env(runner, state: dict):
    """A one-world EnvState from a request's ``sim_state`` (see adapter.sim_state)."""
    from agnostos_mjx.physics.base import PhysicsState
    from agnostos_mjx.runtime.state import EnvState

    m, layout = runner.scene.model, runner.scene.layout
    one = lambda x, dtype=np.float64: np.array(x, dtype)[None]  # noqa: E731
    physics = PhysicsState(
        qpos=one(state["qpos"]), qvel=np.zeros((1, m.nv)), act=np.zeros((1, m.na)),
        ctrl=np.zeros((1, m.nu)), mocap_pos=one(state["mocap_pos"]),
        mocap_quat=one(state["mocap_quat"]), eq_active=m.eq_active0.astype(bool)[None],
        eq_data=np.array(m.eq_data)[None], time=np.zeros(1))
    sensordata = np.asarray(state["sensordata"])
    initial = np.asarray(state["initial_sensordata"])
    return EnvState(
        physics=physics, data=one(sensordata, sensordata.dtype),
        attached=one(state["attached"], bool), carry=(),
        variation=np.array([int(state["variation"])], np.int32),
        gripper=one(state["gripper"]), outcome=np.zeros(1, np.int32),
        key_actions=np.array([int(state["key_actions"])], np.int32),
        sim_steps=np.zeros(1, np.int32), world_steps=np.zeros(1, np.int32), geom_rgba=one(state["geom_rgba"], np.float32),
        initial_data=one(initial, initial.dtype), layout=layout)


class Session:
    """One connection's policy copy, driven through mirror EnvStates."""

    def __init__(self, policy: Policy) -> None:
        self.policy = policy.fork()
        self.episode: tuple | None = None
        self.view: Round | None = None

    def infer(self, obs: dict) -> dict:
        state = obs.get("sim_state") if isinstance(obs, dict) else None
        if not isinstance(state, dict):
            raise ValueError("this server needs the 'sim_state' source (client preset 'sim')")
        runner = runner_for(str(state["task"]))
        env = mirror_env(runner, state)
        episode = (state["task"], int(state["episode_seed"]))
        if self.view is None or self.episode != episode or int(state["key_actions"]) == 0:
            prompt = str(obs.get("prompt", ""))
            self.view = Round.for_policy(self.policy, runner, env, [prompt], [episode[1]])
            self.policy.reset(self.view)
            self.episode = episode
        actions = self.policy.act(self.view.at(env))
        if not bool(np.asarray(actions.valid)[0]):
            return {"actions": np.zeros((0, 8), np.float32)}
        quat = np.asarray(actions.quat, np.float32)[0]
        row = np.concatenate([np.asarray(actions.pos, np.float32)[0], quat[[1, 2, 3, 0]],
                              np.asarray(actions.gripper, np.float32)[:1]])
        return {"actions": row[None]}


def metadata(policy: Any) -> dict:
    """What the server announces on connect (our client adopts ``agnostos_preset``)."""
    return {"server": "agnostos_mjx.serve", "policy": str(getattr(policy, "name", "policy")),
            "agnostos_preset": "sim",
            "action_layout": "x y z qx qy qz qw gripper_open (chunk of 1; empty: no action)",
            "frame": "world", "quat_order": "xyzw", "gripper": "open amount, 1 open, 0 closed"}


def _health_check(connection: ServerConnection, request: Any) -> Any:
    if request.path == "/healthz":
        return connection.respond(http.HTTPStatus.OK, "OK\n")
    return None


class PolicyServer:
    """Serves `policy` on ws://host:port; `start()` runs it on a thread (tests), `run()`
    in the foreground.  Inference runs on one worker thread (JAX and MuJoCo stay
    single-threaded), so the event loop keeps accepting while a request computes."""

    def __init__(self, policy: Any, host: str = "127.0.0.1", port: int = 0,
                 faults: Faults | None = None, stall_s: float = 5.0,
                 on_ready: Callable[[str], None] | None = None,
                 session: Callable[[], Any] | None = None, meta: dict | None = None) -> None:
        self.policy, self.host, self.port = policy, host, port
        # One session (an object with infer(request) -> answer) per connection.
        self.session = session or (lambda: Session(self.policy))
        self.meta = metadata(policy) if meta is None else meta
        self.on_ready = on_ready
        self.faults, self.stall_s = faults, stall_s
        self.requests = 0
        self._worker = concurrent.futures.ThreadPoolExecutor(1, "agnostos-serve")
        self._server: Server | None = None
        self._loop: asyncio.AbstractEventLoop | None = None
        self._ready = threading.Event()

    async def _handler(self, conn: ServerConnection) -> None:
        session = self.session()
        loop = asyncio.get_running_loop()
        await conn.send(wire.packb(self.meta))
        try:
            async for message in conn:
                self.requests += 1
                try:
                    obs = wire.unpackb(message)
                    fault = self.faults(obs) if self.faults else None
                    if fault == "drop":
                        await conn.close()
                        return
                    if fault == "stall":
                        await asyncio.sleep(self.stall_s)
                    if fault == "garbage":
                        await conn.send(b"\xc1 not msgpack")
                        continue
                    if fault == "no_actions":
                        await conn.send(wire.packb({"action": [1, 2, 3]}))
                        continue
                    if fault == "error":
                        raise RuntimeError("injected server fault")
                    answer = await loop.run_in_executor(self._worker, session.infer, obs)
                    await conn.send(wire.packb(answer))
                except ConnectionClosed:
                    return
                except Exception as e:  # openpi's behaviour: the traceback as text, then close
                    log.warning("request failed (%s: %s); closing that connection",
                                type(e).__name__, e)
                    await conn.send(traceback.format_exc())
                    await conn.close(CloseCode.INTERNAL_ERROR, "internal server error; "
                                     "traceback in the previous frame")
                    return
        except ConnectionClosed:
            return

    async def _serve(self) -> None:
        async with serve(self._handler, self.host, self.port, compression=None,
                         max_size=None, ping_interval=None,
                         process_request=_health_check) as server:
            self._server = server
            self.port = server.sockets[0].getsockname()[1]
            self._loop = asyncio.get_running_loop()
            self._ready.set()
            if self.on_ready is not None:
                self.on_ready(self.url)
            await server.serve_forever()

    @property
    def url(self) -> str:
        return f"ws://{self.host}:{self.port}"

    def run(self) -> None:
        asyncio.run(self._serve())

    def start(self) -> PolicyServer:
        threading.Thread(target=self.run, name="agnostos-serve-loop", daemon=True).start()
        if not self._ready.wait(30):
            raise RuntimeError("the policy server did not start")
        return self

    def stop(self) -> None:
        if self._server is not None and self._loop is not None:
            self._loop.call_soon_threadsafe(self._server.close)
        self._worker.shutdown(wait=False)

    def __enter__(self) -> PolicyServer:
        return self.start()

    def __exit__(self, *exc: Any) -> None:
        self.stop()


# ---- HTTP (OpenVLA's deploy.py protocol) --------------------------------------------------
class EpisodeSessions:
    """Sessions keyed by episode (task, episode seed of the request's ``sim_state``): an
    HTTP server has no connection per episode.  The last `keep` episodes are kept."""

    def __init__(self, policy: Any, keep: int = 1024) -> None:
        self.policy, self.keep = policy, keep
        self.sessions: collections.OrderedDict = collections.OrderedDict()

    def infer(self, obs: dict) -> dict:
        state = obs.get("sim_state") if isinstance(obs, dict) else None
        if not isinstance(state, dict):
            raise ValueError("this server needs the 'sim_state' source (client preset 'sim')")
        key = (str(state["task"]), int(state["episode_seed"]))
        if key not in self.sessions:
            self.sessions[key] = Session(self.policy)
            while len(self.sessions) > self.keep:
                self.sessions.popitem(last=False)
        self.sessions.move_to_end(key)
        return self.sessions[key].infer(obs)


class JsonNumpyServer:
    """Serves `policy` (or any `infer(request) -> answer`) as OpenVLA's deploy.py does:
    ``POST /act`` with a json_numpy body, the answer as json_numpy JSON (our policies'
    answers: ``{"actions": chunk}``, preset ``sim``), the JSON string ``"error"`` when
    inference raised; ``GET /`` answers the metadata (JSON), ``GET /healthz`` OK.  On the
    standard library's threading HTTP server; inference runs one request at a time.
    `start()` runs it on a thread (tests), `run()` in the foreground."""

    def __init__(self, policy: Any = None, host: str = "127.0.0.1", port: int = 0,
                 faults: Faults | None = None, stall_s: float = 5.0,
                 infer: Callable[[Any], Any] | None = None, meta: dict | None = None,
                 on_ready: Callable[[str], None] | None = None) -> None:
        if infer is None:
            if policy is None:
                raise ValueError("give a policy or an infer function")
            infer = EpisodeSessions(policy).infer
        self.infer, self.faults, self.stall_s = infer, faults, stall_s
        self.meta = (metadata(policy) if policy is not None else {}) if meta is None else meta
        self.meta = {**self.meta, "transport": "http json_numpy (POST /act)"}
        self.on_ready = on_ready
        self.requests = 0
        self._lock = threading.Lock()
        self._stopping = threading.Event()
        self._httpd = _HTTPServer((host, port), _handler(self))
        self.host, self.port = host, self._httpd.server_address[1]

    @property
    def url(self) -> str:
        return f"http://{self.host}:{self.port}"

    def answer(self, body: bytes) -> tuple[int, bytes] | None:
        """(status, body) of one POST /act, None to close without answering."""
        self.requests += 1
        try:
            obs = json_wire.loads(body)
        except ValueError as e:
            return 400, json_wire.dumps({"detail": f"not json_numpy JSON: {e}"}).encode()
        fault = self.faults(obs) if self.faults else None
        if fault == "drop":
            return None
        if fault == "stall" and self._stopping.wait(self.stall_s):
            return None  # stopped while stalling
        if fault == "garbage":
            return 200, b"\xc1 not json"
        if fault == "no_actions":
            return 200, json_wire.dumps({"action": [1, 2, 3]}).encode()
        if fault == "http_error":
            return 500, b"Internal Server Error"
        try:
            if fault == "error":
                raise RuntimeError("injected server fault")
            with self._lock:
                return 200, json_wire.dumps(self.infer(obs)).encode()
        except Exception as e:  # deploy.py's behaviour: log, answer "error"
            log.warning("request failed (%s: %s); answering \"error\"", type(e).__name__, e)
            return 200, b'"error"'

    def run(self) -> None:
        if self.on_ready is not None:
            self.on_ready(self.url)
        self._httpd.serve_forever()

    def start(self) -> JsonNumpyServer:
        threading.Thread(target=self._httpd.serve_forever, name="agnostos-serve-http",
                         daemon=True).start()
        return self

    def stop(self) -> None:
        self._stopping.set()
        self._httpd.shutdown()
        self._httpd.server_close()

    def __enter__(self) -> JsonNumpyServer:
        return self.start()

    def __exit__(self, *exc: Any) -> None:
        self.stop()


class _HTTPServer(http.server.ThreadingHTTPServer):
    request_queue_size = 256  # a batch's worlds connect at once
    daemon_threads = True


def _handler(server: JsonNumpyServer) -> type[http.server.BaseHTTPRequestHandler]:
    class Handler(http.server.BaseHTTPRequestHandler):
        protocol_version = "HTTP/1.1"
        server_version = "agnostos-mjx"

        def log_message(self, format: str, *args: Any) -> None:  # noqa: A002
            log.debug("%s - " + format, self.address_string(), *args)

        def _send(self, status: int, body: bytes, kind: str = "application/json") -> None:
            self.send_response(status)
            self.send_header("Content-Type", kind)
            self.send_header("Content-Length", str(len(body)))
            self.end_headers()
            self.wfile.write(body)

        def do_GET(self) -> None:  # noqa: N802 - http.server's naming
            if self.path == "/healthz":
                self._send(200, b"OK\n", "text/plain")
            elif self.path == "/":
                self._send(200, json_wire.dumps(server.meta).encode())
            else:
                self._send(404, b'{"detail":"Not Found"}')

        def do_POST(self) -> None:  # noqa: N802
            body = self.rfile.read(int(self.headers.get("Content-Length") or 0))
            if self.path.split("?")[0] != "/act":
                self._send(404, b'{"detail":"Not Found"}')
                return
            result = server.answer(body)
            if result is None:  # "drop": close the connection without a word
                self.close_connection = True
                return
            self._send(*result)

    return Handler
