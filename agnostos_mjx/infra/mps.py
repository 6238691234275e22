"""GPUs of this machine for ``--local-processes N``: placement and private CUDA MPS daemons.

Processes that share a GPU without CUDA MPS time-slice it: 8 processes of 75 worlds each
ran slower together than one process, and 4x faster under MPS (docs/performance.md).
This module decides where each process runs and, for ``--mps auto|on``, starts one MPS
control daemon per shared GPU.
Only the standard library is used: the launcher must not start JAX.

**GPUs** (`visible_gpus`): none unless an NVIDIA driver is there (``nvidia-smi`` on PATH or
``/dev/nvidia0``) and JAX may use it (JAX_PLATFORMS, if set, names cuda or gpu).  Then the
entries of CUDA_VISIBLE_DEVICES (indices or UUIDs, read as CUDA does: up to the first
empty or negative entry; set but empty means none), else one per ``GPU k:`` line of
``nvidia-smi -L``, else one per /dev/nvidia<k>.

**Placement** (`placement`, `child_env`): with G > 1 GPUs, process I runs on GPU I % G
(round-robin); with one GPU or none every process keeps the launcher's environment.

**Daemons** (`Daemons`): one per GPU that two or more processes share, unless a daemon
already answers on $CUDA_MPS_PIPE_DIRECTORY (default /tmp/nvidia-mps): then the processes
use that one as it is (with several GPUs it must see all of them).  "Answers" means its
``control`` socket accepts a connection - a socket file left by a dead daemon does not.
Each private daemon is started as ``nvidia-cuda-mps-control -d`` with CUDA_VISIBLE_DEVICES
set to its GPU and CUDA_MPS_PIPE_DIRECTORY / CUDA_MPS_LOG_DIRECTORY set to
``--out/mps/pipe`` and ``--out/mps/log`` (one GPU) or ``--out/mps/gpu<K>/pipe|log`` (GPU K
of the list; a pipe folder whose socket paths would exceed the 108-byte limit of a UNIX
socket address moves to a short /tmp/agnostos-mps-* folder).  Its processes get the same
two variables and no CUDA_VISIBLE_DEVICES: an MPS server shows the clients only its own
GPUs, renumbered from 0, so the launcher's index would name the wrong device or none
(NVIDIA's MPS documentation, "CUDA_VISIBLE_DEVICES").  After starting, a probe process
creates a CUDA context through the daemon (ctypes on libcuda; skipped without libcuda) and
the daemon must then list an MPS server (a client that cannot reach the daemon runs without
MPS, silently), so a daemon that cannot serve is found before the N processes start.  Each daemon is stopped
with ``echo quit | nvidia-cuda-mps-control`` when the run ends, fails or is interrupted;
``quit`` lets connected clients finish and returns when the daemon has exited, so on Ctrl-C
it is sent at once, without waiting.  A daemon left running in those folders by a launcher
that was killed is reused and then stopped.

The MPS behaviour this relies on (seen on a two-GPU host; docs/performance.md):
``control`` is a SOCK_SEQPACKET socket that accepts a connection; under a daemon started
with CUDA_VISIBLE_DEVICES=1, a client with the variable unset, "0" or GPU 1's UUID got
GPU 1 alone, and one with "1" got CUDA_ERROR_NO_DEVICE (100); ``quit`` with a client still
working returns only when that client ends, which keeps allocating memory meanwhile.
"""

from __future__ import annotations

import contextlib
import errno
import logging
import os
import re
import shutil
import socket
import stat
import subprocess
import sys
import tempfile
import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

log = logging.getLogger("agnostos_mjx.eval")

MODES = ("auto", "on", "off")
CONTROL = "nvidia-cuda-mps-control"
DEFAULT_PIPE = "/tmp/nvidia-mps"  # the daemon's and the clients' default pipe folder
DEV = Path("/dev")
SOCKET_PATH_MAX = 100  # bytes of a pipe folder's longest socket path (sun_path holds 108)
LONGEST_SOCKET = "control_privileged"
START_TIMEOUT_S = 20.0
PROBE_TIMEOUT_S = 60.0
STOP_TIMEOUT_S = 30.0
# Why the warning matters, in the user's terms (the measurement: docs/performance.md).
MEASURED = ("8 processes on one GPU ran slower together than one process, and 4x faster "
            "under CUDA MPS")
# Creates a CUDA context in a client of the daemon of the environment: exit 1 and the CUDA
# error when that fails; "context ok" when it works; nothing when there is no libcuda.
PROBE = r"""
import ctypes, sys
try:
    cuda = ctypes.CDLL("libcuda.so.1")
except OSError:
    sys.exit(0)
dev, ctx = ctypes.c_int(), ctypes.c_void_p()
rc = (cuda.cuInit(0) or cuda.cuDeviceGet(ctypes.byref(dev), 0)
      or cuda.cuDevicePrimaryCtxRetain(ctypes.byref(ctx), dev))
if rc:
    name = ctypes.c_char_p()
    cuda.cuGetErrorName(rc, ctypes.byref(name))
    print(f"CUDA error {rc} ({(name.value or b'?').decode()})")
    sys.exit(1)
cuda.cuDevicePrimaryCtxRelease(dev)
print("context ok")
"""


class MpsError(Exception):
    """CUDA MPS could not be started; the message says why."""


def time_slice_warning(n: int, gpus: int) -> str:
    where = "one GPU" if gpus <= 1 else f"{gpus} GPUs"
    return (f"{n} processes share {where} without CUDA MPS and will time-slice it: "
            f"{MEASURED}")


# ---- which GPUs, and which process runs where ----------------------------------------------
def visible_gpus(environ: Mapping[str, str]) -> tuple[list[str], str]:
    """The GPUs the processes can use, as CUDA_VISIBLE_DEVICES entries, and where that was
    read (or, with none, why there is none)."""
    platforms = environ.get("JAX_PLATFORMS", "").lower()
    if platforms and not {"cuda", "gpu"} & set(platforms.replace(" ", "").split(",")):
        return [], f"JAX_PLATFORMS={environ['JAX_PLATFORMS']}"
    smi = shutil.which("nvidia-smi", path=environ.get("PATH"))
    if smi is None and not (DEV / "nvidia0").exists():
        return [], "no NVIDIA driver (no nvidia-smi on PATH, no /dev/nvidia0)"
    listed = environ.get("CUDA_VISIBLE_DEVICES")
    if listed is not None:
        gpus = []
        for entry in (e.strip() for e in listed.split(",")):
            if not entry or entry.startswith("-"):
                break  # CUDA ignores this entry and every one after it
            gpus.append(entry)
        return gpus, f"CUDA_VISIBLE_DEVICES={listed}"
    if smi is not None:
        with contextlib.suppress(OSError, subprocess.SubprocessError):
            lines = subprocess.run([smi, "-L"], capture_output=True, text=True, timeout=30,
                                   env=dict(environ), check=True).stdout.splitlines()
            count = sum(1 for line in lines if re.match(r"GPU \d+:", line))
            if count:
                return [str(k) for k in range(count)], "nvidia-smi -L"
    count = sum(1 for p in DEV.glob("nvidia*") if re.fullmatch(r"nvidia\d+", p.name))
    return [str(k) for k in range(count)], "/dev/nvidia*" if count else "no GPU found"


def placement(n: int, gpus: int) -> list[int | None]:
    """The GPU (index into the visible ones) of each of `n` processes: I % G, or None for
    all when there is no GPU."""
    return [i % gpus if gpus else None for i in range(n)]


def shared(where: Sequence[int | None]) -> list[int]:
    """The GPUs that two or more processes run on, in order."""
    return sorted({k for k in where if k is not None and where.count(k) > 1})


@dataclass(frozen=True)
class Daemon:
    """A private MPS control daemon serving one GPU (a CUDA_VISIBLE_DEVICES entry)."""

    gpu: str
    pipe: Path
    log: Path

    def env(self, base: Mapping[str, str]) -> dict[str, str]:
        """The daemon's own environment."""
        return {**base, "CUDA_VISIBLE_DEVICES": self.gpu,
                "CUDA_MPS_PIPE_DIRECTORY": str(self.pipe),
                "CUDA_MPS_LOG_DIRECTORY": str(self.log)}


def child_env(base: Mapping[str, str], gpu: str | None, daemon: Daemon | None) -> dict[str, str]:
    """A process's environment: `base` with the variables of its daemon (clients of an MPS
    server must not set CUDA_VISIBLE_DEVICES: the server renumbers its GPU to 0), else its
    GPU as CUDA_VISIBLE_DEVICES (None: left as in `base`)."""
    env = dict(base)
    if daemon is not None:
        env.pop("CUDA_VISIBLE_DEVICES", None)
        env["CUDA_MPS_PIPE_DIRECTORY"] = str(daemon.pipe)
        env["CUDA_MPS_LOG_DIRECTORY"] = str(daemon.log)
    elif gpu is not None:
        env["CUDA_VISIBLE_DEVICES"] = gpu
    return env


def daemon_dirs(out: Path, k: int, gpus: int) -> tuple[Path, Path]:
    """(pipe, log) folders of the daemon of GPU `k` of `gpus` in run folder `out`."""
    base = out.resolve() / "mps"
    if gpus > 1:
        base = base / f"gpu{k}"
    return base / "pipe", base / "log"


# ---- daemons -------------------------------------------------------------------------------
def answers(pipe: Path) -> bool:
    """Whether an MPS control daemon listens on `pipe`/control (a socket file left by a dead
    one refuses the connection)."""
    path = pipe / "control"
    try:
        if not stat.S_ISSOCK(path.stat().st_mode):
            return False
    except OSError:
        return False
    for kind in (socket.SOCK_SEQPACKET, socket.SOCK_STREAM):  # the daemon's is SEQPACKET
        with socket.socket(socket.AF_UNIX, kind) as s:
            s.settimeout(2.0)
            try:
                s.connect(str(path))
                return True
            except OSError as e:
                if e.errno != errno.EPROTOTYPE:
                    return False
    return False


def running_daemon(environ: Mapping[str, str]) -> Path | None:
    """The pipe folder of an MPS daemon the processes would use as they are, if one answers."""
    pipe = Path(environ.get("CUDA_MPS_PIPE_DIRECTORY") or DEFAULT_PIPE)
    return pipe if answers(pipe) else None


def _tail(path: Path, lines: int = 3) -> str:
    try:
        text = path.read_text(errors="replace").strip().splitlines()[-lines:]
    except OSError:
        return ""
    return " | ".join(text)


class Daemons:
    """The private daemons of one run: `start` them, `stop` (asynchronous, at once) on
    Ctrl-C, `close` at the end (stops any still running and waits for the stops)."""

    def __init__(self, environ: Mapping[str, str]) -> None:
        self.environ = dict(environ)
        self.running: dict[int, Daemon] = {}
        self._stopping: list[tuple[Daemon, subprocess.Popen]] = []
        self._tmp: set[Path] = set()  # short pipe folders made in /tmp, removed at close
        self.binary: str | None = None

    def start(self, out: Path, gpus: Sequence[str], which: Sequence[int]) -> None:
        """A daemon for each GPU index in `which` (of the visible `gpus`); MpsError if any
        cannot start or serve (those already started stay in `running`, for `close`)."""
        self.binary = shutil.which(CONTROL, path=self.environ.get("PATH"))
        if self.binary is None:
            raise MpsError(f"{CONTROL} is not on PATH (it comes with the NVIDIA driver's "
                           "compute utilities)")
        for k in which:
            pipe, logs = daemon_dirs(out, k, len(gpus))
            if len(os.fsencode(pipe / LONGEST_SOCKET)) > SOCKET_PATH_MAX:
                pipe = Path(tempfile.mkdtemp(prefix=f"agnostos-mps-gpu{k}-", dir="/tmp"))
                self._tmp.add(pipe)
                log.info("MPS pipe folder of GPU %s: %s (--out's path is too long for a "
                         "UNIX socket)", gpus[k], pipe)
            pipe.mkdir(parents=True, exist_ok=True)
            logs.mkdir(parents=True, exist_ok=True)
            daemon = Daemon(gpus[k], pipe, logs)
            if answers(pipe):
                log.info("reusing the MPS daemon left running in %s", pipe)
            else:
                (pipe / "control").unlink(missing_ok=True)  # a dead daemon's socket
                self._launch(daemon)
            self.running[k] = daemon
        for daemon in self.running.values():
            self._probe(daemon)

    def _launch(self, daemon: Daemon) -> None:
        assert self.binary is not None
        try:
            proc = subprocess.run([self.binary, "-d"], env=daemon.env(self.environ),
                                  stdin=subprocess.DEVNULL, capture_output=True, text=True,
                                  timeout=START_TIMEOUT_S)
        except (OSError, subprocess.TimeoutExpired) as e:
            raise MpsError(f"{CONTROL} -d for GPU {daemon.gpu}: {e}") from None
        said = " ".join((proc.stdout + proc.stderr).split())
        if proc.returncode != 0:
            raise MpsError(f"{CONTROL} -d for GPU {daemon.gpu} exited with "
                           f"{proc.returncode}" + (f": {said}" if said else ""))
        deadline = time.monotonic() + START_TIMEOUT_S
        while not (daemon.pipe / "control").exists():
            if time.monotonic() > deadline:
                tail = _tail(daemon.log / "control.log")
                raise MpsError(f"the MPS daemon of GPU {daemon.gpu} made no control socket "
                               f"in {daemon.pipe} within {START_TIMEOUT_S:.0f} s"
                               + (f"; {daemon.log}/control.log: {tail}" if tail else ""))
            time.sleep(0.05)
        log.info("CUDA MPS daemon started for GPU %s (pipe %s, log %s)", daemon.gpu,
                 daemon.pipe, daemon.log)

    def _probe(self, daemon: Daemon) -> None:
        env = child_env(self.environ, None, daemon)
        try:
            proc = subprocess.run([sys.executable, "-c", PROBE], env=env, capture_output=True,
                                  text=True, timeout=PROBE_TIMEOUT_S, stdin=subprocess.DEVNULL)
        except (OSError, subprocess.TimeoutExpired) as e:
            raise MpsError(f"no CUDA context through the MPS daemon of GPU {daemon.gpu}: "
                           f"{e}") from None
        if proc.returncode != 0:
            said = " ".join((proc.stdout + proc.stderr).split())[-300:]
            tail = _tail(daemon.log / "control.log")
            raise MpsError(f"no CUDA context through the MPS daemon of GPU {daemon.gpu}: "
                           f"{said or f'exit {proc.returncode}'}"
                           + (f"; {daemon.log}/control.log: {tail}" if tail else ""))
        if "context ok" not in proc.stdout:
            log.info("no libcuda to check the MPS daemon of GPU %s with", daemon.gpu)
            return
        # A client that cannot reach the daemon runs without MPS, silently: the server the
        # probe's context started (it outlives its clients) must be listed.
        try:
            listed = subprocess.run([self.binary or CONTROL], input="get_server_list\n",
                                    env=daemon.env(self.environ), capture_output=True,
                                    text=True, timeout=START_TIMEOUT_S).stdout.split()
        except (OSError, subprocess.TimeoutExpired) as e:
            raise MpsError(f"get_server_list of the MPS daemon of GPU {daemon.gpu}: {e}") from None
        if not listed:
            raise MpsError(f"a CUDA context came up without the MPS daemon of GPU {daemon.gpu} "
                           f"(pipe {daemon.pipe}): the processes could not reach it")

    def of(self, k: int | None) -> Daemon | None:
        return None if k is None else self.running.get(k)

    def stop(self) -> None:
        """Ask every running daemon to quit, without waiting (safe while clients run: the
        daemon takes no new clients and exits once the connected ones have ended)."""
        for k, daemon in list(self.running.items()):
            assert self.binary is not None
            try:
                proc = subprocess.Popen([self.binary], env=daemon.env(self.environ),
                                        stdin=subprocess.PIPE, stdout=subprocess.DEVNULL,
                                        stderr=subprocess.DEVNULL, text=True,
                                        start_new_session=True)  # a 2nd Ctrl-C spares it
                assert proc.stdin is not None
                proc.stdin.write("quit\n")
                proc.stdin.close()
            except OSError as e:
                log.warning("could not stop the MPS daemon of GPU %s (%s): %s", daemon.gpu,
                            daemon.pipe, e)
                continue
            finally:
                del self.running[k]
            self._stopping.append((daemon, proc))

    def close(self, timeout_s: float = STOP_TIMEOUT_S) -> None:
        """Stop every daemon still running and wait (up to `timeout_s`) for the stops."""
        self.stop()
        deadline = time.monotonic() + timeout_s
        stuck = set()
        for daemon, proc in self._stopping:
            try:
                proc.wait(timeout=max(deadline - time.monotonic(), 0.1))
            except subprocess.TimeoutExpired:
                log.warning("the MPS daemon of GPU %s (%s) has not quit after %.0f s; stop "
                            "it with: echo quit | CUDA_MPS_PIPE_DIRECTORY=%s %s", daemon.gpu,
                            daemon.pipe, timeout_s, daemon.pipe, CONTROL)
                stuck.add(daemon.pipe)
                continue
            if proc.returncode == 0:
                log.info("CUDA MPS daemon of GPU %s stopped", daemon.gpu)
            else:
                log.warning("echo quit | %s for GPU %s (%s) exited with %d", CONTROL,
                            daemon.gpu, daemon.pipe, proc.returncode)
        self._stopping.clear()
        for path in self._tmp - stuck:
            shutil.rmtree(path, ignore_errors=True)
        self._tmp &= stuck
