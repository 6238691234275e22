"""``--policy remote``: a policy served over openpi's websocket protocol or over HTTP with
json_numpy bodies (OpenVLA's and OpenVLA-OFT's ``vla-scripts/deploy.py``).

The URL's scheme picks the transport:

* ``ws://`` / ``wss://``: openpi's ``WebsocketPolicyServer`` / ``WebsocketClientPolicy``
  protocol.  On connect the server sends its metadata (a msgpack map); then each request
  is one msgpack observation map and each answer a msgpack map with ``"actions"``; a
  server that fails sends the traceback as a text frame and closes.  Arrays travel as in
  wire.py.  Every world of a batch has a connection of its own, opened at its first
  request and kept for its episode (so a stateful server sees one episode per
  connection).
* ``http://`` / ``https://``: ``POST`` of the observation map as JSON with json_numpy
  arrays (json_wire.py) to the URL's path (``/act`` when it has none), one request per
  key action on a fresh connection; the answer is JSON (OpenVLA: the action array
  itself, hence the ``openvla`` presets' ``action_key=None``).  A status other than 200,
  or the JSON string ``"error"`` (what deploy.py answers when its model raised), is a
  server error.  At start-up a ``GET /`` checks that the server is there; a JSON object
  answered there is taken as its metadata (our reference server's ``agnostos_preset``).

All requests of a step are in flight at once on one background asyncio loop.  While they
are, the evaluator simulates other tasks (`act_steps` yields the future).  A failure
touches only its world: a refused or dropped connection or a server error ends that
episode as ``remote_error``, no answer within ``timeout_s`` as ``remote_timeout``, an
unreadable answer as ``bad_remote_output``; the run goes on.

A chunk's first ``execute`` rows (an adapter option, default 1) run as that many
consecutive key actions of the world before it asks the server again.
"""

from __future__ import annotations

import asyncio
import collections
import concurrent.futures
import contextlib
import ssl
import threading
import time
from collections.abc import Generator
from typing import TYPE_CHECKING, Any
from urllib.parse import urlparse

import numpy as np

from agnostos_mjx.infra import settings
from agnostos_mjx.policies.base import Policy, Round
from agnostos_mjx.remote import json_wire
from agnostos_mjx.remote.adapter import (
    BadAnswer,
    apply_row,
    lowdim,
    make_adapter,
    parse_rows,
    request,
)
from agnostos_mjx.remote.adapter import sim_state as world_sim_state
from agnostos_mjx.remote.options import OpenVLAOptions, RemoteOptions
from agnostos_mjx.sim.actions import KeyActions

if TYPE_CHECKING:
    from agnostos_mjx.runtime.observation import RLBenchObservation

SCHEMES = ("ws", "wss", "http", "https")


class RemotePolicyError(ValueError):
    """The server cannot be used (bad URL, unreachable at start-up)."""


class ServerError(Exception):
    """The server answered that it failed (a traceback frame, an HTTP error, "error")."""


class _Loop:
    """One asyncio loop on a daemon thread, shared by all remote policies of the process."""

    _instance: _Loop | None = None
    _lock = threading.Lock()

    def __init__(self) -> None:
        self.loop = asyncio.new_event_loop()
        threading.Thread(target=self.loop.run_forever, name="agnostos-remote",
                         daemon=True).start()

    @classmethod
    def get(cls) -> _Loop:
        with cls._lock:
            if cls._instance is None:
                cls._instance = cls()
            return cls._instance

    def submit(self, coro: Any) -> concurrent.futures.Future:
        return asyncio.run_coroutine_threadsafe(coro, self.loop)


def check_url(url: str | None, policy: str = "remote") -> str:
    if not url:
        where = "--policy-url " if policy == "remote" else "--policy-arg url="
        raise RemotePolicyError(f"--policy {policy} needs {where}ws://HOST:PORT or "
                                f"{where}http://HOST:PORT (or $AGNOSTOS_POLICY_URL)")
    parsed = urlparse(url)
    if parsed.scheme not in SCHEMES or not parsed.hostname:
        raise RemotePolicyError(f"--policy-url must look like ws://HOST:PORT (openpi) or "
                                f"http://HOST:PORT[/act] (OpenVLA), got {url!r}")
    return url


def _summary(text: str) -> str:
    lines = [line for line in text.strip().splitlines() if line.strip()]
    return lines[-1][:300] if lines else "(empty)"


# ---- transports ---------------------------------------------------------------------------
class WebsocketTransport:
    """openpi's protocol: one connection per world, msgpack both ways."""

    kind = "websocket"

    def __init__(self, url: str) -> None:
        self.url = url

    async def _open(self) -> tuple[Any, Any]:
        """A connection and the server's metadata (its first message).  Keepalive pings
        are off: a server busy with inference may not answer them; `timeout_s` bounds
        waits."""
        from websockets.asyncio.client import connect

        from agnostos_mjx.remote import wire

        conn = await connect(self.url, compression=None, max_size=None, ping_interval=None,
                             open_timeout=None)
        first = await conn.recv()
        if isinstance(first, str):
            await conn.close()
            raise ConnectionError(f"server error: {first.strip().splitlines()[-1:]}")
        return conn, wire.unpackb(first)

    async def probe(self) -> Any:
        conn, metadata = await self._open()
        await conn.close()
        return metadata

    def encode(self, obs: dict) -> bytes:
        from agnostos_mjx.remote import wire

        return wire.packb(obs)

    async def send(self, conns: dict, world: int, data: bytes) -> bytes:
        if world not in conns:
            conns[world], _ = await self._open()
        await conns[world].send(data)
        reply = await conns[world].recv()
        if isinstance(reply, str):  # openpi servers send their traceback as text
            raise ServerError(_summary(reply))
        return reply

    def decode(self, reply: bytes) -> Any:
        from agnostos_mjx.remote import wire

        return wire.unpackb(reply)

    @staticmethod
    async def drop(conns: dict, world: int) -> None:
        conn = conns.pop(world, None)
        if conn is not None:
            try:
                async with asyncio.timeout(1.0):
                    await conn.close()
            except Exception:  # noqa: BLE001 - it is gone either way
                pass


class HttpTransport:
    """OpenVLA's deploy.py protocol: POST of a json_numpy body, one connection per
    request (``Connection: close``: no idle connection for a server to drop between key
    actions).  A minimal HTTP/1.1 client on asyncio streams, so a timeout cancels it."""

    kind = "http"

    def __init__(self, url: str) -> None:
        parsed = urlparse(url)
        self.url = url
        self.host = parsed.hostname or "localhost"
        self.port = parsed.port or (443 if parsed.scheme == "https" else 80)
        self.path = (parsed.path if parsed.path not in ("", "/") else "/act") + \
            (f"?{parsed.query}" if parsed.query else "")
        self.ssl = ssl.create_default_context() if parsed.scheme == "https" else None
        self.netloc = parsed.netloc.rpartition("@")[2]

    async def _request(self, method: str, path: str, body: bytes | None = None
                       ) -> tuple[int, dict[str, str], bytes]:
        reader, writer = await asyncio.open_connection(self.host, self.port, ssl=self.ssl)
        try:
            head = (f"{method} {path} HTTP/1.1\r\nHost: {self.netloc}\r\n"
                    f"User-Agent: agnostos-mjx\r\nAccept: application/json\r\n"
                    f"Connection: close\r\n")
            if body is not None:
                head += f"Content-Type: application/json\r\nContent-Length: {len(body)}\r\n"
            writer.write(head.encode("latin-1") + b"\r\n" + (body or b""))
            await writer.drain()
            try:
                return await _read_response(reader, method)
            except asyncio.IncompleteReadError:
                raise ConnectionError("the connection closed in the middle of the answer"
                                      ) from None
        finally:
            writer.close()
            with contextlib.suppress(Exception):
                async with asyncio.timeout(1.0):
                    await writer.wait_closed()

    async def probe(self) -> Any:
        status, headers, body = await self._request("GET", "/")
        meta: dict[str, Any] = {}
        if status == 200 and "json" in headers.get("content-type", ""):
            with contextlib.suppress(ValueError):
                found = json_wire.loads(body)
                if isinstance(found, dict):
                    meta.update(found)
        if headers.get("server"):
            meta.setdefault("http_server", headers["server"])
        return meta

    def encode(self, obs: dict) -> bytes:
        return json_wire.dumps(obs).encode()

    async def send(self, conns: dict, world: int, data: bytes) -> bytes:
        status, _, body = await self._request("POST", self.path, data)
        if status != 200:
            raise ServerError(f"HTTP {status}: {_summary(body.decode('utf-8', 'replace'))}")
        return body

    def decode(self, body: bytes) -> Any:
        answer = json_wire.loads(body)
        if isinstance(answer, str):
            if answer.strip() == "error":
                raise ServerError('it answered "error" (deploy.py\'s answer when the model '
                                  'raised; the traceback is in the server\'s log)')
            answer = json_wire.loads(answer)  # deploy.py's double-encoded answers
        return answer

    @staticmethod
    async def drop(conns: dict, world: int) -> None:
        return None


async def _read_response(reader: asyncio.StreamReader, method: str
                         ) -> tuple[int, dict[str, str], bytes]:
    status_line = await reader.readline()
    if not status_line:
        raise ConnectionError("the server closed the connection without an answer")
    parts = status_line.decode("latin-1").split(None, 2)
    if len(parts) < 2 or not parts[0].startswith("HTTP/") or not parts[1].isdigit():
        raise ConnectionError(f"not an HTTP answer: {status_line[:80]!r}")
    status = int(parts[1])
    headers: dict[str, str] = {}
    while True:
        line = await reader.readline()
        if line in (b"\r\n", b"\n", b""):
            break
        key, _, value = line.decode("latin-1").partition(":")
        headers[key.strip().lower()] = value.strip()
    if method == "HEAD" or status in (204, 304) or 100 <= status < 200:
        return status, headers, b""
    if "chunked" in headers.get("transfer-encoding", "").lower():
        body = bytearray()
        while True:
            size = int((await reader.readline()).split(b";")[0].strip() or b"0", 16)
            if size == 0:
                while (await reader.readline()) not in (b"\r\n", b"\n", b""):
                    pass  # trailers
                return status, headers, bytes(body)
            body += await reader.readexactly(size)
            await reader.readexactly(2)
    if "content-length" in headers:
        return status, headers, await reader.readexactly(int(headers["content-length"]))
    return status, headers, await reader.read()


def make_transport(url: str) -> WebsocketTransport | HttpTransport:
    return HttpTransport(url) if urlparse(url).scheme in ("http", "https") \
        else WebsocketTransport(url)


# ---- the policy ---------------------------------------------------------------------------
class RemotePolicy(Policy):
    """Sends each running world's observation (mapped by an Adapter) to the server and
    executes the key actions in its answers.  Privileged only with the ``sim`` preset,
    which sends the simulator's state (for a server that runs a privileged policy).

    Its options (`RemoteOptions`): the URL (else $AGNOSTOS_POLICY_URL), the preset
    (rlbench, libero, droid, xicm, openvla, openvla_oft, sim, or auto: what the server's
    metadata names as ``agnostos_preset``, else rlbench over websockets and openvla over
    HTTP), `keys` (a server key -> source mapping replacing the preset's), the Adapter
    fields that override the preset's, and the timeouts."""

    name = "remote"
    Options = RemoteOptions  # its options' type, and their defaults
    # In dense mode each row is one control step's target (the adapter's execute and
    # relative options apply as for key actions).
    action_modes = ("keyaction", "dense")

    def __init__(self, options: RemoteOptions | None = None) -> None:
        o = options or self.Options()
        self.url = check_url(o.url or settings.POLICY_URL.get(), self.name)
        self.timeout_s = o.timeout_s
        self.transport = make_transport(self.url)
        self._loop = _Loop.get()
        try:
            self.metadata = self._loop.submit(self._probe(o.connect_timeout_s)).result()
        except Exception as e:  # noqa: BLE001 - any failure means "cannot use it"
            raise RemotePolicyError(f"cannot reach the policy server at {self.url}: "
                                    f"{type(e).__name__}: {e}") from None
        meta = self.metadata if isinstance(self.metadata, dict) else {}
        preset = o.preset
        if preset == "auto":
            default = "openvla" if self.transport.kind == "http" else "rlbench"
            preset = str(meta.get("agnostos_preset", default))
        self.preset = preset
        self.adapter = make_adapter(preset, o.keys, **o.adapter_options())
        self.observation_spec = self.adapter.spec()
        self.privileged = self.adapter.wants_sim_state
        served = meta.get("policy")
        self.name = f"{self.name}[{served}]" if served else self.name
        # Shared by the copies the evaluator makes per task: one report for the run.
        self.stats: collections.Counter = collections.Counter()
        self._conns: dict[int, Any] = {}
        self._queue: dict[int, collections.deque] = {}
        self._failed = np.zeros(0, np.int32)  # each world's Outcome code once it failed
        self._errors: dict[int, str] = {}

    async def _probe(self, timeout_s: float) -> Any:
        async with asyncio.timeout(timeout_s):
            return await self.transport.probe()

    # ---- the plug-in interface ------------------------------------------------------------
    def reset(self, view: Round) -> None:
        self._close(self._conns)
        b = view.batch
        self.instructions = list(view.instructions)
        self._seeds = view.episode_seeds
        self._conns = {}
        self._queue = {}
        self._errors = {}
        self._failed = np.zeros(b, np.int32)

    def act_steps(self, view: Round) -> Generator[concurrent.futures.Future, Any, KeyActions]:
        """`act` as a generator that yields the future of the step's requests.  Worlds
        with rows left of their last chunk execute the next one without a request; a world
        whose request failed gets no action, its end_reason the failure's Outcome code."""
        b = len(self._failed)
        running = np.nonzero(view.running[:b] & (self._failed == 0))[0]
        ask = np.array([w for w in running if not self._queue.get(int(w))], np.int64)
        sources = None
        if len(ask) or (self.adapter.relative and len(running)):
            sources = lowdim(view.proprioception)
        payloads = self._requests(view, ask, sources)
        future = self._loop.submit(self._exchange(self._conns, payloads))
        yield future
        for w, (code, answer) in zip(ask, future.result()):
            if code == 0:
                try:
                    self._queue[int(w)] = collections.deque(parse_rows(self.adapter, answer))
                    continue
                except Exception as e:  # noqa: BLE001 - garbage of any kind
                    code, answer = self._bad_output(e)
            self._fail(int(w), code, answer)
        pos = np.zeros((b, 3), np.float32)
        quat = np.tile(np.array([1.0, 0, 0, 0], np.float32), (b, 1))
        grip = np.ones(b, np.float32)
        valid = np.zeros(b, bool)
        for w in running:
            queue = self._queue.get(int(w))
            if self._failed[w] or not queue:  # failed, or an empty chunk: no action
                continue
            pose = sources["gripper_pose"][w] if sources is not None else None
            pos[w], quat[w], grip[w] = apply_row(self.adapter, queue.popleft(), pose)
            valid[w] = True
        return KeyActions(pos, quat, grip, valid, end_reason=self._failed.copy())

    def episode_info(self, world: int) -> dict:
        return {"error": self._errors[world]} if world in self._errors else {}

    def report(self) -> dict:
        """Requests, failures by outcome and mean round trip, for results.json
        (``remote``) and the console summary."""
        answered = self.stats["answered"]
        meta = self.metadata if isinstance(self.metadata, dict) else {}
        return {"remote": {
            "url": self.url, "preset": self.preset,
            "server": {str(k): str(v) for k, v in meta.items()},
            "requests": self.stats["requests"], "answered": answered,
            "failures": {k: v for k, v in self.stats.items()
                         if k not in ("requests", "answered", "round_trip_s")},
            "mean_round_trip_ms": round(1000 * self.stats["round_trip_s"]
                                        / max(answered, 1), 3)}}

    # ---- pieces ---------------------------------------------------------------------------
    def _requests(self, view: Round, worlds: np.ndarray, sources: dict | None
                  ) -> list[tuple[int, bytes]]:
        """Encoded requests of `worlds` (rendering what the adapter needs, once)."""
        if not len(worlds):
            return []
        assert sources is not None
        observation: RLBenchObservation | None = None
        if self.observation_spec is not None:
            observation = view.observation
        sources = dict(sources, instruction=self.instructions)
        if self.privileged:
            sources["sim_state"] = {int(w): world_sim_state(view.episodes, view.env, int(w),
                                                            self._seeds[int(w)])
                                    for w in worlds}
        return [(int(w), self.transport.encode(request(self.adapter, int(w), sources,
                                                       observation)))
                for w in worlds]

    async def _exchange(self, conns: dict, payloads: list[tuple[int, bytes]]
                        ) -> list[tuple[int, Any]]:
        return await asyncio.gather(*(self._one(conns, w, data) for w, data in payloads))

    async def _one(self, conns: dict, world: int, data: bytes) -> tuple[int, Any]:
        """(0, the decoded answer) or (an Outcome code, why) for one world's request."""
        from agnostos_mjx.runtime.outcome import Outcome

        t0 = time.perf_counter()
        self.stats["requests"] += 1
        try:
            async with asyncio.timeout(self.timeout_s):
                reply = await self.transport.send(conns, world, data)
        except TimeoutError:
            await self.transport.drop(conns, world)
            return Outcome.REMOTE_TIMEOUT, f"no answer within {self.timeout_s:g} s"
        except ServerError as e:
            await self.transport.drop(conns, world)
            return Outcome.REMOTE_ERROR, f"server error: {e}"
        except Exception as e:  # noqa: BLE001 - refused, reset, closed, bad handshake
            await self.transport.drop(conns, world)
            return Outcome.REMOTE_ERROR, f"{type(e).__name__}: {e}"
        self.stats["answered"] += 1
        self.stats["round_trip_s"] += time.perf_counter() - t0
        try:
            return 0, self.transport.decode(reply)
        except ServerError as e:
            return Outcome.REMOTE_ERROR, f"server error: {e}"
        except Exception as e:  # noqa: BLE001 - not msgpack / JSON
            return self._bad_output(e)

    def _close(self, conns: dict) -> None:
        """Close a finished batch's connections in the background."""
        for world in list(conns):
            self._loop.submit(self.transport.drop(conns, world))

    @staticmethod
    def _bad_output(error: Exception) -> tuple[int, str]:
        from agnostos_mjx.runtime.outcome import Outcome

        kind = "" if isinstance(error, BadAnswer) else f"{type(error).__name__}: "
        return Outcome.BAD_REMOTE_OUTPUT, f"{kind}{error}"[:300]

    def _fail(self, world: int, code: int, why: str) -> None:
        from agnostos_mjx.runtime.outcome import Outcome

        self._failed[world] = code
        self._errors[world] = why
        self._queue.pop(world, None)
        self.stats[Outcome(code).label] += 1


class OpenVLAPolicy(RemotePolicy):
    """``--policy openvla``: an OpenVLA / OpenVLA-OFT ``deploy.py`` server over HTTP
    (preset ``openvla`` unless told otherwise; ``openvla_oft`` for OFT's keys).  The URL
    comes from ``url`` (``--policy-arg url=...``), else $AGNOSTOS_POLICY_URL."""

    name = "openvla"
    Options = OpenVLAOptions
