"""Serve one of our policies over openpi's websocket protocol: ``python -m agnostos_mjx.serve``.

    python -m agnostos_mjx.serve --policy oracle --port 8000
    python -m agnostos_mjx.eval --policy remote --policy-url ws://localhost:8000 --tasks lamp_on

See agnostos_mjx/remote/server.py for what a request must carry (the ``sim`` preset) and
how each connection runs its own copy of the policy.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence

from agnostos_mjx.infra.cli import HelpFormatter, setup_logging
from agnostos_mjx.infra.settings import configure_jax


def build_parser() -> argparse.ArgumentParser:
    from agnostos_mjx.evaluation.config import policy_arg

    p = argparse.ArgumentParser(prog="python -m agnostos_mjx.serve", formatter_class=HelpFormatter,
                                description="Serve a policy over openpi's websocket protocol.")
    p.add_argument("--policy", default="oracle",
                   help="oracle, retrieval, xicm or 'module:attr' / 'file.py:attr'")
    p.add_argument("--policy-arg", action="append", type=policy_arg, default=None,
                   metavar="KEY=VALUE", help="an option of the policy, as for agnostos_mjx.eval "
                                             "(--policy-arg help lists them and exits)")
    p.add_argument("--host", default="127.0.0.1", help="address to listen on (0.0.0.0: all)")
    p.add_argument("--port", type=int, default=8000, help="TCP port (0: any free one)")
    p.add_argument("--gpu-mem-fraction", type=float, default=None,
                   help="cap JAX's GPU memory pool at this fraction (0: no preallocation); "
                        "default $AGNOSTOS_GPU_MEM_FRACTION, else JAX's 75%%")
    p.add_argument("--quiet", action="store_true", help="warnings only")
    return p


def main(argv: Sequence[str] | None = None) -> int:
    configure_jax()
    args = build_parser().parse_args(argv)
    setup_logging(args.quiet)
    from agnostos_mjx.policies import make_policy
    from agnostos_mjx.policies.base import policy_help

    options = dict(args.policy_arg or [])
    if "help" in options:
        print(policy_help(args.policy))
        return 0
    from agnostos_mjx.infra.gpu import apply_memory_limit

    apply_memory_limit(args.gpu_mem_fraction)  # before JAX starts
    from agnostos_mjx.remote.server import PolicyServer

    try:  # a built-in policy's options are checked as eval's (policies/options.py)
        policy = make_policy(args.policy, **options)
    except (KeyError, ImportError, ValueError, TypeError) as e:
        print(f"error: cannot load policy {args.policy!r}: {e}", file=sys.stderr)
        return 2
    name = getattr(policy, "name", args.policy)
    server = PolicyServer(policy, args.host, args.port,
                          on_ready=lambda url: print(f"serving {name} on {url}", flush=True))
    try:
        server.run()
    except OSError as e:
        print(f"error: cannot listen on {args.host}:{args.port}: {e}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        return 130
    return 0


if __name__ == "__main__":
    sys.exit(main())
