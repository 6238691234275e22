"""Build the seen-demo memory X-ICM selects from: ``python -m agnostos_mjx.xicm.build_memory``.

Reads a demonstration bank, adds the dynamics-model features of every demo
when a checkpoint is given, and writes one compressed .npz (by default the
file shipped with the package).

Examples::

    python -m agnostos_mjx.xicm.build_memory --bank data/seen_bank
    python -m agnostos_mjx.xicm.build_memory --bank data/seen_bank --checkpoint agnostos_mjx/assets/dynamics
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence
from pathlib import Path

from agnostos_mjx.data.bank import BankError, DemoBank
from agnostos_mjx.infra.cli import HelpFormatter, setup_logging
from agnostos_mjx.infra.settings import configure_jax
from agnostos_mjx.xicm.memory import DemoMemory, MemoryFileError, default_memory_path


def main(argv: Sequence[str] | None = None) -> int:
    configure_jax()
    p = argparse.ArgumentParser(prog="python -m agnostos_mjx.xicm.build_memory",
                                formatter_class=HelpFormatter,
                                description="Build the seen-demo memory (texts, key actions, "
                                            "object centres, selection features).")
    p.add_argument("--bank", type=Path, required=True, help="demonstration bank directory")
    p.add_argument("--checkpoint", type=Path, default=None,
                   help="dynamics model: an export (python -m agnostos_mjx.train.export) or a "
                        "training run directory; adds lang / vis.in / vis.out features")
    p.add_argument("--out", type=Path, default=default_memory_path(), help="memory file")
    p.add_argument("--extend", type=Path, default=None,
                   help="an existing memory to add the bank's demos to (e.g. new tasks); its "
                        "demos of tasks the bank holds are replaced (re-recorded experts)")
    a = p.parse_args(argv)
    setup_logging(False)
    try:
        bank = DemoBank(a.bank)
        features = None
        if a.checkpoint is not None:
            from agnostos_mjx.dynamics.checkpoint import CheckpointError
            from agnostos_mjx.xicm.dynamics_selector import bank_features

            try:
                features = bank_features(bank, a.checkpoint)
            except CheckpointError as err:
                print(f"error: {err}", file=sys.stderr)
                return 2
        memory = DemoMemory.from_bank(bank, features)
        if a.extend is not None:
            old = DemoMemory.load(a.extend)
            memory = DemoMemory.concat(old.without_tasks(set(memory.task.tolist())), memory)
    except (BankError, MemoryFileError) as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    a.out.parent.mkdir(parents=True, exist_ok=True)
    memory.save(a.out)
    size = a.out.stat().st_size / 1e6
    print(f"{a.out}: {len(memory)} demos of {len(set(memory.task.tolist()))} tasks, features "
          f"{sorted(memory.features) or 'none'}, {size:.1f} MB")
    return 0


if __name__ == "__main__":
    sys.exit(main())
