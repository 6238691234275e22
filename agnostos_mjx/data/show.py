"""Print demonstrations of a bank in X-ICM's text form: ``python -m agnostos_mjx.data.show``.

Examples::

    python -m agnostos_mjx.data.show data/seen_bank                       # summary per task
    python -m agnostos_mjx.data.show data/seen_bank --task close_jar --index 0 3
    python -m agnostos_mjx.data.show data/seen_bank --task close_jar --all
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence
from pathlib import Path

from agnostos_mjx.data.bank import BankError, DemoBank
from agnostos_mjx.infra.cli import HelpFormatter


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="python -m agnostos_mjx.data.show",
                                formatter_class=HelpFormatter,
                                description="Show a demonstration bank: a summary, or demos "
                                            "as the exact in-context text X-ICM prompts with.")
    p.add_argument("bank", type=Path, help="bank directory (made by agnostos_mjx.data.generate)")
    p.add_argument("--task", help="task whose demos to print (default: summary of all tasks)")
    p.add_argument("--index", type=int, nargs="*", default=[0],
                   help="positions of the demos to print within the task")
    p.add_argument("--all", action="store_true", help="print every demo of --task")
    return p


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        bank = DemoBank(args.bank)
        if args.task is None:
            print(f"{args.bank}: {len(bank)} demos, cameras {', '.join(bank.cameras)}")
            for name, entry in bank.manifest["tasks"].items():
                print(f"  {name:32s} {entry['demos']:5d} demos "
                      f"({entry['failed_attempts']} failed attempts re-sampled)")
            return 0
        count = len(bank.arrays(args.task)["index"])
        for i in range(count) if args.all else args.index:
            print(bank.demo(args.task, i).text())
    except (BankError, IndexError, OSError) as err:  # one line, no traceback
        print(f"error: {err}", file=sys.stderr)
        return 2
    except KeyError as err:
        print(f"error: {args.bank}: incomplete bank (no {err.args[0]!r}); regenerate it",
              file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
