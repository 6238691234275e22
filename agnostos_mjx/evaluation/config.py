"""EvalConfig, in parts, and the command line generated from it.

An evaluation is configured in four parts: `ProtocolConfig` (what is evaluated and how the
worlds run), `PolicyConfig` (which policy, its arguments), `XicmConfig` (the built-in X-ICM
and retrieval policies' LLM client and demo selection) and `RunConfig` (the run's folder,
logging, processes and devices); `EvalConfig` holds one of each (``cfg.protocol.seeds``).
Each option is written once, as a field of its part: its type and default there, its help,
flag and argparse details in the field's metadata (see `option`).  Option names are
unique across the parts, so a flat ``{name: value}`` still names a config (`EvalConfig.of`,
results.json written before the parts).  `build_parser` turns the fields into ``python -m
agnostos_mjx.eval``'s options in HELP_ORDER, and `parse_config` turns parsed arguments
back into an EvalConfig.
"""

from __future__ import annotations

import argparse
import contextlib
import copy
import json
from collections.abc import Iterator
from dataclasses import MISSING, Field, asdict, dataclass, field, fields
from pathlib import Path
from typing import Any

from agnostos_mjx.infra.cli import HelpFormatter, atomic_write, prog
from agnostos_mjx.infra.mps import MODES as MPS_MODES
from agnostos_mjx.llm.client import DEFAULT_TIMEOUT_S
from agnostos_mjx.llm.server import KINDS as LLM_SERVER_KINDS
from agnostos_mjx.physics import BACKENDS, RENDERERS

VARIATION_MODES = ("protocol", "all", "zero")
# Option groups of --help (None: the main options).
SCALE = "several devices and hosts (see README, Scale out)"
LLM = "X-ICM and retrieval"
DENSE = "dense control (see README, Dense control)"
ACTION_MODES = ("keyaction", "dense")


class UsageError(Exception):
    """A bad command line or output directory: reported in one line, exit code 2."""


# ---- converters of option values -----------------------------------------------------------
def int_list(text: str) -> list[int]:
    """Comma-separated integers, duplicates dropped (``--seeds 0,1,2``)."""
    try:
        values = [int(p) for p in text.split(",") if p.strip()]
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"expected comma-separated integers, got {text!r}") from None
    if not values:
        raise argparse.ArgumentTypeError("expected at least one integer")
    return list(dict.fromkeys(values))


def positive_int(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected an integer, got {text!r}") from None
    if value < 1:
        raise argparse.ArgumentTypeError(f"expected a positive integer, got {value}")
    return value


def positive_float(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number, got {text!r}") from None
    if not value > 0:
        raise argparse.ArgumentTypeError(f"expected a positive number, got {text}")
    return value


def variation_mode(text: str) -> str:
    if text in VARIATION_MODES or text.isdigit():
        return text
    raise argparse.ArgumentTypeError(
        f"expected one of {', '.join(VARIATION_MODES)} or a variation number, got {text!r}")


def policy_arg(text: str) -> tuple[str, Any]:
    """KEY=VALUE, VALUE parsed as JSON where it can be (``--policy-arg model="qwen"``);
    ``help`` alone asks for the policy's options (`policy_help`)."""
    if text == "help":
        return "help", True
    key, sep, value = text.partition("=")
    if not sep or not key:
        raise argparse.ArgumentTypeError(f"expected KEY=VALUE, got {text!r}")
    try:
        return key, json.loads(value)
    except json.JSONDecodeError:
        return key, value


# ---- the configuration -------------------------------------------------------------------
def option(default: Any, help: str, *, name: str | None = None, flag: str | None = None,
           group: str | None = None, **argparse_kwargs: Any) -> Any:
    """A field of a part of EvalConfig that is also a command-line option.

    `name` is the option's name across all the parts (argparse's dest, the key of a flat
    results.json "config"): the field's name unless given; the flag is ``--name`` with
    dashes unless `flag` says otherwise; `help` and `argparse_kwargs` (type, choices,
    metavar) go to ``add_argument``; `group` is the --help section.  The default's type
    sets the option's form: False is a switch, a list is given as comma-separated text (its
    `type` parses it), a dict collects repeated KEY=VALUE options."""
    metadata = {"help": help, "name": name, "flag": flag, "group": group,
                "argparse": argparse_kwargs}
    if isinstance(default, list | dict):
        return field(default_factory=lambda: copy.copy(default), metadata=metadata)
    return field(default=default, metadata=metadata)


@dataclass
class ProtocolConfig:
    """What is evaluated, and how the worlds run: the AGNOSTOS protocol's tasks, seeds and
    episodes, the action mode, and the physics, planner and renderer that carry it out."""

    tasks: str = option(
        "unseen", "comma-separated task names and/or split names (seen, unseen, "
                  "unseen_level1, unseen_level2, all)")
    seeds: list[int] = option([0, 1, 2], "comma-separated evaluation seeds", type=int_list)
    episodes: int = option(25, "episodes per task and seed", type=positive_int)
    batch: int = option(
        75, "worlds simulated at once; the episodes of all seeds of a task are pooled and "
            "run in chunks of this size", type=positive_int)
    backend: str = option(
        "auto", "physics backend (auto: MJX-warp on a CUDA GPU for batches of >= 4096 worlds, "
                "else native MuJoCo on all CPU threads, which is faster below that and "
                "bit-reproducible)", choices=BACKENDS)
    planner: str = option(
        "auto", "where key actions are planned (IK + path of every world): device = one "
                "jitted program shared by all tasks, on the GPU when there is one (auto there); "
                "host = numpy float64 (auto on a CPU-only machine, bit for bit the recorded "
                "CPU results)", choices=("auto", "host", "device"))
    renderer: str = option(
        "auto", "where a policy's camera observations render: warp = MJX-Warp's batch ray "
                "tracer on the GPU, beside any physics backend (auto wherever JAX has a CUDA "
                "GPU and warp-lang is installed); cpu = MuJoCo's OpenGL renderer on CPU "
                "threads (auto elsewhere); overrides the policy's ObservationSpec.renderer; "
                "the route taken is in results.json", choices=RENDERERS)
    variations: str = option(
        "protocol", "protocol: unseen tasks use variation 0, seen tasks sample one per "
                    "episode; all: sample for every task; zero: always 0; N: always N",
        type=variation_mode)
    action_mode: str = option(
        "keyaction", "keyaction: one key action per policy step, planned and executed to "
                     "rest (the AGNOSTOS / X-ICM protocol); dense: one end-effector target "
                     "per control step at --control-hz, by IK and physics for one control "
                     "period, for policies that declare it (see agnostos_mjx/runtime/dense.py)",
        group=DENSE, choices=ACTION_MODES)
    control_hz: float | None = option(
        None, "dense: control rate (default 20, RLBench's and LIBERO's observation rate; the "
              "period is rounded to whole 5 ms physics steps)", group=DENSE,
        type=positive_float, metavar="HZ")
    dense_steps: int | None = option(
        None, "dense: step budget in control steps, after which an episode ends as "
              "max_steps (default: 25 key actions x 2 s = 50 s, 1000 steps at 20 Hz)",
        group=DENSE, type=positive_int, metavar="N")
    execute: int | None = option(
        None, "dense: rows of a policy's action chunk run open loop before it is asked again "
              "(default: the whole chunk); remote policies take theirs as --policy-arg "
              "execute=K", group=DENSE, type=positive_int, metavar="K")


@dataclass
class PolicyConfig:
    """Which policy acts and the arguments its factory gets."""

    spec: str = option(
        "auto", "auto (xicm when an LLM is configured, else retrieval), xicm, retrieval, "
                "oracle, or 'module:attr' / 'file.py:attr' naming a Policy class, factory or "
                "instance (see agnostos_mjx/policies/base.py)", name="policy")
    args: dict[str, Any] = option(
        {}, "an option of the policy (VALUE parsed as JSON if it can be); repeatable; "
            "--policy-arg help lists a policy's options and exits", name="policy_args",
        flag="--policy-arg", type=policy_arg,
        metavar="KEY=VALUE")
    url: str | None = option(
        None, "the policy server of --policy remote or openvla: ws://... speaks openpi's "
              "websocket protocol, http://... POSTs json_numpy bodies to /act (OpenVLA's "
              "deploy.py); default $AGNOSTOS_POLICY_URL; its adapter options (preset, keys, "
              "rotation, execute, timeout_s, action_index, ...) go in --policy-arg, see "
              "agnostos_mjx/remote/adapter.py", name="policy_url", metavar="URL")


@dataclass
class XicmConfig:
    """The options of the built-in X-ICM and retrieval policies: the LLM client (X-ICM) and
    the in-context demo selection (both)."""

    llm_url: str | None = option(
        None, "OpenAI-compatible base URL, e.g. http://localhost:8000/v1, or 'vllm:' for an "
              "in-process vLLM engine (extra 'vllm') (default: $AGNOSTOS_LLM_URL); the key "
              "comes from $AGNOSTOS_LLM_API_KEY or $OPENAI_API_KEY", group=LLM)
    llm_model: str | None = option(
        None, "model name on that server (default: $AGNOSTOS_LLM_MODEL)", group=LLM)
    llm_cache: str | None = option(
        None, "response cache directory (default: <out>/llm_cache); reruns and --resume "
              "reuse answers, a shipped cache replays a run offline", group=LLM)
    llm_concurrency: int | None = option(
        None, "LLM requests in flight at once (default: the server's slot count where it "
              "publishes one (llama.cpp: 1 unless started with --parallel N), capping this "
              "flag too; else 64 for vLLM, which batches on the GPU, and 8 for other "
              "servers)", group=LLM, type=positive_int)
    llm_timeout: float = option(
        DEFAULT_TIMEOUT_S, "seconds without a byte from the LLM server before a request is "
                           "given up (answers are streamed, so this is silence, not total "
                           "time; not retried, since the server may still be computing). "
                           "Covers prompt processing before the first token: seconds on a "
                           "GPU, up to minutes for long prompts on a CPU",
        group=LLM, type=positive_float)
    llm_server_kind: str = option(
        "auto", "which sampling field names to send: vllm (repetition_penalty; also "
                "SGLang), llamacpp (repeat_penalty; llama.cpp and llama-cpp-python), openai "
                "(no penalty field); auto detects it in the start-up check",
        group=LLM, choices=LLM_SERVER_KINDS)
    selection: str = option(
        "auto", "in-context demo selection: random, text (instruction trigrams), dynamics "
                "features lang, vis.in, vis.out joined with '+', or auto (lang+vis.out when "
                "the memory has dynamics features, else text)", group=LLM)
    num_demos: int = option(18, "K, in-context demonstrations per prompt", group=LLM,
                            type=positive_int)
    ddim_steps: int | None = option(
        None, "DDIM steps of a query's dynamics features (default 10: as good as the "
              "original's 50 for selection and 5x cheaper, see docs/performance.md)",
        group=LLM, type=positive_int)
    memory: str | None = option(
        None, "seen-demo memory .npz (default: the one shipped with the package)", group=LLM)


@dataclass
class RunConfig:
    """The run's plumbing: its folder, logging, videos and report, the GPU memory, and the
    processes, devices and hosts it is spread over."""

    out: str | None = option(
        None, "output directory; default results/<policy>-<timestamp>, <policy> being the "
              "policy run (retrieval or xicm under auto)")
    resume: bool = option(
        False, "continue the run in --out (required): skip episodes already in its "
               "episodes.jsonl")
    fail_fast: bool = option(
        False, "re-raise policy exceptions instead of recording policy_error")
    quiet: bool = option(
        False, "no progress bar, warnings-only logging (the table is still printed)")
    video: str | None = option(
        None, "MP4 per episode in <out>/videos for episodes 0..N-1 of each task and seed, or "
              "the failures (see agnostos_mjx/evaluation/video.py; needs PyAV)",
        metavar="first:N|failures[:N]")
    video_cameras: str | None = option(
        None, "comma-separated cameras side by side (default front,overhead,wrist)")
    compare: str | None = option(
        None, "add a column of published numbers: 'X-ICM 7B', 'X-ICM 72B', pi0, VoxPoser or "
              "RVT2", group=LLM)
    gpu_mem_fraction: float | None = option(
        None, "cap JAX's GPU memory pool at F of the card, 0: no preallocation (default "
              "$AGNOSTOS_GPU_MEM_FRACTION; 0.35 when the policy or LLM server is on this "
              "machine; else JAX's 75%%); see agnostos_mjx/infra/gpu.py", type=float, metavar="F")
    devices: int | None = option(
        None, "local accelerators a batch's worlds (MJX-jax) and the dynamics features are "
              "sharded over (default: all)", group=SCALE, type=positive_int, metavar="N")
    num_processes: int = option(
        1, "processes (hosts) sharing the run: process I runs tasks I, I+N, ... into "
           "--out/proc-I; then --merge", group=SCALE, type=positive_int, metavar="N")
    process_id: int = option(0, "this process's index, 0..N-1", group=SCALE, type=int,
                             metavar="I")
    coordinator: str | None = option(
        None, "process 0's address: each process calls jax.distributed.initialize with it "
              "(one JAX cluster; sharding stays on each host's local devices); without it "
              "the processes run independently", group=SCALE, metavar="HOST:PORT")
    local_processes: int | None = option(
        None, "run as N processes on this machine (each takes the next task no other has "
              "taken, longest first, see --task-queue; with G GPUs process I on GPU I mod G, "
              "see --mps; logs in --out/proc-I.log), then merge; default: 8 per NVIDIA GPU "
              "(at most 16 and half the cores), the fastest count measured on GPU hosts, "
              "and 1 without a GPU (see docs/performance.md)",
        group=SCALE, type=positive_int, metavar="N")
    task_queue: str | None = option(
        None, "a folder shared by processes on one machine: instead of every N-th task, "
              "this process takes the next task that no process has claimed there, longest "
              "expected first (--local-processes passes --out/queue to its processes)",
        group=SCALE, metavar="DIR")
    mps: str = option(
        "auto", "CUDA MPS for --local-processes: for each GPU that several processes share, "
                "auto starts a private MPS daemon (pipe and log folders in --out/mps) and "
                "stops it at exit, unless one already runs, and warns once if it cannot; on: "
                "the same, but exit 2 if it cannot; off: none, the processes time-slice the "
                "GPU (several times slower than under MPS: docs/performance.md). With several GPUs process I "
                "runs on GPU I mod G; no effect without a GPU", group=SCALE, choices=MPS_MODES)
    merge: bool = option(
        False, "only merge --out/proc-*/episodes.jsonl into --out's results files "
               "(episodes.jsonl, results.json/.csv/.md/.png)", group=SCALE)
    overlap_tasks: int = option(
        3, "tasks evaluated at once in a process when the policy can wait (X-ICM, "
           "retrieval, served policies): while one task waits on its LLM requests or, on "
           "native physics, on its key actions (run on a thread pool), the others go on; "
           "on a GPU the tasks at once share the demo selection's and the device "
           "planner's calls (1: one task at a time; on the CPU results do not depend on "
           "it, on a GPU they round as the shared calls do, the same in every run with "
           "this value)", group=LLM,
        type=positive_int)

@dataclass
class EvalConfig:
    """One evaluation run, in parts; every field of a part is a command-line option."""

    protocol: ProtocolConfig = field(default_factory=ProtocolConfig)
    policy: PolicyConfig = field(default_factory=PolicyConfig)
    xicm: XicmConfig = field(default_factory=XicmConfig)
    run: RunConfig = field(default_factory=RunConfig)

    @classmethod
    def of(cls, **options: Any) -> EvalConfig:
        """The config of options by their names (``EvalConfig.of(tasks="lamp_on")``); a
        TypeError for a name no part has."""
        unknown = set(options) - set(OPTIONS)
        if unknown:
            raise TypeError(f"no such option: {', '.join(sorted(unknown))}")
        given: dict[str, dict[str, Any]] = {part: {} for part in PARTS}
        for name, value in options.items():
            part, f = OPTIONS[name]
            given[part][f.name] = value
        return cls(**{part: PARTS[part](**values) for part, values in given.items()})

    @classmethod
    def from_dict(cls, config: dict[str, Any]) -> EvalConfig:
        """The config of results.json's "config": nested by part (asdict), or flat as
        written before the parts (its options by name); keys no longer known are dropped."""
        if not any(isinstance(config.get(part), dict) for part in PARTS):
            return cls.of(**{k: v for k, v in config.items() if k in OPTIONS})
        parts = {}
        for part, values in config.items():
            if part in PARTS and isinstance(values, dict):
                known = {f.name for f in fields(PARTS[part])}
                parts[part] = PARTS[part](**{k: v for k, v in values.items() if k in known})
        return cls(**parts)

    def options(self) -> dict[str, Any]:
        """Every option by its name (the inverse of `of`)."""
        return {name: getattr(getattr(self, part), f.name)
                for name, (part, f) in OPTIONS.items()}

    def with_options(self, **options: Any) -> EvalConfig:
        """A copy with `options` (by name) changed."""
        return EvalConfig.of(**{**copy.deepcopy(self.options()), **options})


# The parts, and each option by name: (its part, its field).
PARTS: dict[str, Any] = {f.name: f.default_factory for f in fields(EvalConfig)}
OPTIONS: dict[str, tuple[str, Field]] = {
    f.metadata["name"] or f.name: (part, f) for part, cls in PARTS.items() for f in fields(cls)}
# --help's order: the parts group the options by what they configure, --help by use.
HELP_ORDER = (
    "policy", "policy_args", "policy_url", "gpu_mem_fraction", "tasks", "seeds", "episodes",
    "batch", "backend", "planner", "renderer", "variations", "action_mode", "control_hz",
    "dense_steps", "execute", "out", "resume", "fail_fast", "quiet", "video", "video_cameras",
    "devices", "num_processes", "process_id", "coordinator", "local_processes", "task_queue",
    "mps", "merge", "llm_url", "llm_model", "llm_cache", "llm_concurrency", "llm_timeout",
    "llm_server_kind", "overlap_tasks", "selection", "num_demos", "ddim_steps", "memory",
    "compare")
assert sorted(HELP_ORDER) == sorted(OPTIONS), "HELP_ORDER must name every option once"


def _default(f: Field) -> Any:
    return f.default_factory() if f.default is MISSING else f.default  # type: ignore[misc]


def build_parser(defaults: bool = True) -> argparse.ArgumentParser:
    """The command line of EvalConfig's options (see `option`), in HELP_ORDER, and the
    hidden ``--spec FILE``; without `defaults` a parse holds only the options given."""
    parser = argparse.ArgumentParser(
        prog=prog("agnostos_mjx.eval"),
        description="Evaluate a policy on AGNOSTOS tasks (X-ICM protocol) and write "
                    "episodes.jsonl, results.json, results.csv and results.md.",
        formatter_class=HelpFormatter)
    groups: dict[str | None, Any] = {None: parser}
    for name in HELP_ORDER:
        f = OPTIONS[name][1]
        meta, default = f.metadata, _default(f)
        kwargs = dict(meta["argparse"])
        if default is False:
            kwargs["action"] = "store_true"
        elif isinstance(default, list):
            default = ",".join(map(str, default))  # parsed by the option's type
        elif isinstance(default, dict):
            kwargs["action"], default = "append", None
        if meta["group"] not in groups:
            groups[meta["group"]] = parser.add_argument_group(meta["group"])
        groups[meta["group"]].add_argument(
            meta["flag"] or "--" + name.replace("_", "-"), dest=name, help=meta["help"],
            default=default if defaults else argparse.SUPPRESS, **kwargs)
    # The processes of --local-processes read the run from the file their launcher wrote
    # (write_spec), not from flags parsed again; not for people, so not in --help.
    parser.add_argument("--spec", metavar="FILE", help=argparse.SUPPRESS,
                        default=None if defaults else argparse.SUPPRESS)
    return parser


def parse_config(argv: list[str] | None = None) -> EvalConfig:
    """EvalConfig of a command line (argparse exits on a bad one); with ``--spec FILE``,
    the config of FILE with the options given beside it."""
    args = vars(build_parser().parse_args(argv))
    if args.pop("spec") is None:
        return EvalConfig.of(**_values(args))
    parser = build_parser(defaults=False)
    given = vars(parser.parse_args(argv))
    try:
        return read_spec(Path(given.pop("spec"))).with_options(**_values(given))
    except UsageError as e:
        parser.error(str(e))


def _values(args: dict[str, Any]) -> dict[str, Any]:
    """Parsed options as EvalConfig's values: repeated KEY=VALUE pairs as a dict."""
    return {name: dict(value or []) if isinstance(_default(OPTIONS[name][1]), dict) else value
            for name, value in args.items()}


def write_spec(path: Path, cfg: EvalConfig) -> None:
    """`cfg` to `path` (results.json's "config" form), whole or not at all."""
    atomic_write(path, json.dumps(asdict(cfg), indent=1) + "\n")


def read_spec(path: Path) -> EvalConfig:
    """The config `write_spec` wrote; a UsageError when it cannot be read."""
    try:
        return EvalConfig.from_dict(json.loads(path.read_text(encoding="utf-8")))
    except (OSError, ValueError, TypeError) as e:
        raise UsageError(f"--spec {path}: {e}") from None


def policy_spec(cfg: EvalConfig) -> tuple[str, str]:
    """(the policy `cfg` runs, a one-line explanation of auto's choice or "")."""
    from agnostos_mjx.llm.client import LLMConfig

    if cfg.policy.spec != "auto":
        return cfg.policy.spec, ""
    llm = cfg.xicm
    if LLMConfig.from_env(llm.llm_url, llm.llm_model) is not None:
        return "xicm", "an LLM is configured: running X-ICM"
    return "retrieval", ("no LLM configured (set --llm-url/--llm-model or AGNOSTOS_LLM_URL/"
                         "AGNOSTOS_LLM_MODEL for X-ICM): running the retrieval baseline")


@contextlib.contextmanager
def loading_policy(spec: str) -> Iterator[None]:
    """Errors of building the policy `spec` (its file, its model, its LLM) as a UsageError,
    one line: the run's processes and the warm-up's policy step report them alike."""
    from agnostos_mjx.llm.client import LLMConfigError
    from agnostos_mjx.xicm.memory import MemoryFileError

    try:
        yield
    except (LLMConfigError, MemoryFileError) as e:
        raise UsageError(str(e)) from None
    except (KeyError, ImportError, ValueError, TypeError) as e:
        raise UsageError(f"cannot load policy {spec!r}: "
                         f"{e.args[0] if isinstance(e, KeyError) else e}") from None


def resolve_policy(cfg: EvalConfig) -> tuple[str, dict[str, Any], str]:
    """(policy spec, factory kwargs, a one-line explanation) for `cfg`.  A built-in policy's
    options are those its options type takes from the run's flags (`from_config`), then
    the --policy-arg pairs, checked here (an OptionsError in one line); any other policy
    gets the --policy-arg pairs as they are."""
    from agnostos_mjx.policies.base import options_type
    from agnostos_mjx.policies.options import parse_options

    spec, note = policy_spec(cfg)
    kind = options_type(spec)
    if kind is None:
        return spec, dict(cfg.policy.args), note
    options = parse_options(kind, {**kind.from_config(cfg), **cfg.policy.args}, spec)
    return spec, options.values(), note
