"""Stage 4: export a trained dynamics model in the compact shipping format.

Writes what feature extraction needs - the autoencoder's encoder, the text encoder
and the UNet, as float16 in one compressed params.npz - and export.json (configs,
sampling settings, format version).  `Pipeline.load`, the X-ICM `DynamicsSelector`,
`build_memory --checkpoint` and `evaluate --run` all read the export directory.

    python -m agnostos_mjx.train.export --run runs/dyn --out agnostos_mjx/assets/dynamics
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Any

from agnostos_mjx.dynamics.checkpoint import CheckpointError
from agnostos_mjx.dynamics.export import export, load_export
from agnostos_mjx.dynamics.export_format import PARAMS_FILE
from agnostos_mjx.infra.settings import configure_jax
from agnostos_mjx.xicm.dynamics_selector import default_checkpoint_path


def parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="python -m agnostos_mjx.train.export",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument(
        "--run",
        type=Path,
        required=True,
        help="dynamics run directory (python -m agnostos_mjx.train.dynamics)",
    )
    p.add_argument(
        "--ae",
        type=Path,
        help="autoencoder run directory (default: the one the dynamics run recorded)",
    )
    p.add_argument(
        "--out",
        type=Path,
        default=default_checkpoint_path(),
        help="export directory, replaced file by file (default: the package's shipped "
        f"model, {default_checkpoint_path()})",
    )
    return p


def main(argv: list[str] | None = None) -> dict[str, Any]:
    configure_jax()
    args = parser().parse_args(argv)
    try:
        info = export(args.run, args.out, args.ae)
        load_export(args.out)  # read it back: the files, hash and every shape check out
    except CheckpointError as err:
        print(f"error: {err}", file=sys.stderr)
        raise SystemExit(2) from err
    size = (args.out / PARAMS_FILE).stat().st_size
    print(
        f"{args.out}: {info['parameters'] / 1e6:.2f} M parameters (float16), "
        f"{PARAMS_FILE} {size / 1e6:.1f} MB, from {info['source']['run']} "
        f"step {info['source']['step']}"
    )
    return info


if __name__ == "__main__":
    main()
