"""``--policy remote``: a policy served over openpi's websocket protocol.

Protocol (openpi's ``WebsocketPolicyServer`` / ``WebsocketClientPolicy``): on connect the
server sends its metadata (a msgpack map); then each request is one msgpack observation
map and each answer a msgpack map with ``"actions"``; a server that fails sends the
traceback as a text frame and closes.  Arrays travel as in wire.py.

Every world of a batch has a connection of its own, opened at its first request and kept
for its episode (so a stateful server sees one episode per connection); all requests of a
step are in flight at once on one background asyncio loop.  While they are, the evaluator
simulates other tasks (`act_steps` yields the future).  A failure touches only its world:
a refused or dropped connection or a server error ends that episode as ``remote_error``,
no answer within ``timeout_s`` as ``remote_timeout``, an unreadable answer as
``bad_remote_output``; the run goes on.
"""

from __future__ import annotations

import asyncio
import collections
import concurrent.futures
import threading
import time
from collections.abc import Generator, Sequence
from typing import TYPE_CHECKING, Any
from urllib.parse import urlparse

import numpy as np
from websockets.asyncio.client import ClientConnection, connect

from agnostos_mjx.remote import wire
from agnostos_mjx.remote.adapter import BadAnswer, lowdim, make_adapter, parse_action, request
from agnostos_mjx.remote.adapter import sim_state as world_sim_state
from agnostos_mjx.tasks.base import KeyActions

if TYPE_CHECKING:
    from agnostos_mjx.observation import RLBenchObservation
    from agnostos_mjx.runtime.env import Episodes
    from agnostos_mjx.runtime.state import EnvState

DEFAULT_TIMEOUT_S = 60.0  # first requests may wait for a model's compilation


class RemotePolicyError(ValueError):
    """The server cannot be used (bad URL, unreachable at start-up)."""


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


def check_url(url: str | None) -> str:
    if not url:
        raise RemotePolicyError("--policy remote needs --policy-url ws://HOST:PORT")
    parsed = urlparse(url)
    if parsed.scheme not in ("ws", "wss") or not parsed.hostname:
        raise RemotePolicyError(f"--policy-url must look like ws://HOST:PORT, got {url!r}")
    return url


async def _open(url: str) -> tuple[ClientConnection, Any]:
    """A connection and the server's metadata (its first message).  Keepalive pings are
    off: a server busy with inference may not answer them; `timeout_s` bounds waits."""
    conn = await connect(url, compression=None, max_size=None, ping_interval=None,
                         open_timeout=None)
    first = await conn.recv()
    if isinstance(first, str):
        await conn.close()
        raise ConnectionError(f"server error: {first.strip().splitlines()[-1:]}")
    return conn, wire.unpackb(first)


async def _probe(url: str, timeout_s: float) -> Any:
    async with asyncio.timeout(timeout_s):
        conn, metadata = await _open(url)
        await conn.close()
    return metadata


def _summary(text: str) -> str:
    lines = [line for line in text.strip().splitlines() if line.strip()]
    return lines[-1][:300] if lines else "(empty)"


class RemotePolicy:
    """Sends each running world's observation (mapped by an Adapter) to the server and
    executes the key action in its answer.

    `preset`: rlbench, libero, droid, sim, or auto (what the server's metadata names as
    ``agnostos_preset``, else rlbench); `keys`: a server key -> source mapping (or its
    JSON) replacing the preset's; other keyword arguments set Adapter fields (height,
    width, action_index, quat_order, gripper, action_key)."""

    name = "remote"

    def __init__(self, url: str | None = None, preset: str = "auto",
                 keys: dict[str, str] | str | None = None,
                 timeout_s: float = DEFAULT_TIMEOUT_S, connect_timeout_s: float = 30.0,
                 **adapter_options: Any) -> None:
        self.url = check_url(url)
        self.timeout_s = float(timeout_s)
        self._loop = _Loop.get()
        try:
            self.metadata = self._loop.submit(_probe(self.url, connect_timeout_s)).result()
        except Exception as e:  # noqa: BLE001 - any failure means "cannot use it"
            raise RemotePolicyError(f"cannot reach the policy server at {self.url}: "
                                    f"{type(e).__name__}: {e}") from None
        meta = self.metadata if isinstance(self.metadata, dict) else {}
        if preset == "auto":
            preset = str(meta.get("agnostos_preset", "rlbench"))
        self.preset = preset
        self.adapter = make_adapter(preset, keys, **adapter_options)
        served = meta.get("policy")
        self.name = f"remote[{served}]" if served else "remote"
        # Shared by the copies the evaluator makes per task: one report for the run.
        self.stats: collections.Counter = collections.Counter()
        self._conns: dict[int, ClientConnection] = {}
        self.end_reasons = np.zeros(0, np.int32)
        self._errors: dict[int, str] = {}

    # ---- the plug-in interface ------------------------------------------------------------
    def reset(self, episodes: Episodes, env: EnvState, instructions: list[str],
              episode_seeds: Sequence[int] | None = None) -> None:
        self._close(self._conns)
        b = len(instructions)
        self.instructions = list(instructions)
        self._seeds = list(episode_seeds) if episode_seeds is not None else list(range(b))
        self._conns = {}
        self._errors = {}
        self.end_reasons = np.zeros(b, np.int32)

    def act(self, episodes: Episodes, env: EnvState,
            observation: RLBenchObservation | None = None) -> KeyActions:
        from agnostos_mjx.policies.planning import run_blocking

        return run_blocking(self.act_steps(episodes, env, observation))

    def act_steps(self, episodes: Episodes, env: EnvState,
                  observation: RLBenchObservation | None = None
                  ) -> Generator[concurrent.futures.Future, Any, KeyActions]:
        """`act` as a generator that yields the future of the step's requests."""
        b = len(self.end_reasons)
        worlds = np.nonzero(~env.done[:b] & (self.end_reasons == 0))[0]
        payloads = self._requests(episodes, env, worlds, observation)
        future = self._loop.submit(self._exchange(self._conns, payloads))
        yield future
        pos = np.zeros((b, 3), np.float32)
        quat = np.tile(np.array([1.0, 0, 0, 0], np.float32), (b, 1))
        grip = np.ones(b, np.float32)
        valid = np.zeros(b, bool)
        for w, (code, reply) in zip(worlds, future.result()):
            if code == 0:
                try:
                    action = parse_action(self.adapter, wire.unpackb(reply))
                except Exception as e:  # noqa: BLE001 - garbage of any kind
                    code, reply = self._bad_output(e)
                else:
                    if action is not None:
                        pos[w], quat[w], grip[w] = action
                        valid[w] = True
                    continue
            self._fail(int(w), code, reply)
        return KeyActions(pos, quat, grip, valid)

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
    def _requests(self, episodes: Episodes, env: EnvState, worlds: np.ndarray,
                  observation: RLBenchObservation | None) -> list[tuple[int, bytes]]:
        """Encoded requests of `worlds` (rendering what the adapter needs, once)."""
        if not len(worlds):
            return []
        spec = self.adapter.spec()
        if spec is not None and observation is None:
            observation = episodes.observe(env, spec)
        sources: dict[str, Any] = lowdim(episodes.observer.proprioception(env))
        sources["instruction"] = self.instructions
        if self.adapter.wants_sim_state:
            sources["sim_state"] = {int(w): world_sim_state(episodes, env, int(w),
                                                            self._seeds[int(w)])
                                    for w in worlds}
        return [(int(w), wire.packb(request(self.adapter, int(w), sources, observation)))
                for w in worlds]

    async def _exchange(self, conns: dict[int, ClientConnection],
                        payloads: list[tuple[int, bytes]]) -> list[tuple[int, Any]]:
        return await asyncio.gather(*(self._one(conns, w, data) for w, data in payloads))

    async def _one(self, conns: dict[int, ClientConnection], world: int, data: bytes
                   ) -> tuple[int, Any]:
        """(0, answer bytes) or (an Outcome code, why) for one world's request."""
        from agnostos_mjx.runtime.outcome import Outcome

        t0 = time.perf_counter()
        self.stats["requests"] += 1
        try:
            async with asyncio.timeout(self.timeout_s):
                if world not in conns:
                    conns[world], _ = await _open(self.url)
                await conns[world].send(data)
                reply = await conns[world].recv()
        except TimeoutError:
            await self._drop(conns, world)
            return Outcome.REMOTE_TIMEOUT, f"no answer within {self.timeout_s:g} s"
        except Exception as e:  # noqa: BLE001 - refused, reset, closed, bad handshake
            await self._drop(conns, world)
            return Outcome.REMOTE_ERROR, f"{type(e).__name__}: {e}"
        if isinstance(reply, str):  # openpi servers send their traceback as text
            await self._drop(conns, world)
            return Outcome.REMOTE_ERROR, f"server error: {_summary(reply)}"
        self.stats["answered"] += 1
        self.stats["round_trip_s"] += time.perf_counter() - t0
        return 0, reply

    @staticmethod
    async def _drop(conns: dict[int, ClientConnection], world: int) -> None:
        conn = conns.pop(world, None)
        if conn is not None:
            try:
                async with asyncio.timeout(1.0):
                    await conn.close()
            except Exception:  # noqa: BLE001 - it is gone either way
                pass

    def _close(self, conns: dict[int, ClientConnection]) -> None:
        """Close a finished batch's connections in the background."""
        for world in list(conns):
            self._loop.submit(self._drop(conns, world))

    @staticmethod
    def _bad_output(error: Exception) -> tuple[int, str]:
        from agnostos_mjx.runtime.outcome import Outcome

        kind = "" if isinstance(error, BadAnswer) else f"{type(error).__name__}: "
        return Outcome.BAD_REMOTE_OUTPUT, f"{kind}{error}"[:300]

    def _fail(self, world: int, code: int, why: str) -> None:
        from agnostos_mjx.runtime.outcome import Outcome

        self.end_reasons[world] = code
        self._errors[world] = why
        self.stats[Outcome(code).label] += 1
