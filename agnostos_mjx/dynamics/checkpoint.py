"""Orbax checkpoints of a training run: flat arrays + JSON metadata per step.

Orbax writes each step to a temporary directory and renames it when complete,
so an interrupted save never leaves a half checkpoint that resume would pick.
Arrays are stored flat under their parameter paths ("unet.down.0.res.conv1.kernel"),
which lets a mismatch be reported by name instead of as a pytree-structure error.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import jax
import numpy as np
from flax import nnx

from agnostos_mjx.dynamics.config import diff


class CheckpointError(RuntimeError):
    """A checkpoint is missing or does not fit the model/config asked for."""


def flatten(tree: Any, prefix: str) -> dict[str, Any]:
    leaves, _ = jax.tree_util.tree_flatten_with_path(tree)
    return {f"{prefix}.{jax.tree_util.keystr(p, simple=True, separator='.')}": v for p, v in leaves}


def unflatten(template: Any, arrays: dict[str, Any], prefix: str, where: Path) -> Any:
    """Fill `template`'s structure from `arrays`, naming every missing or misshapen entry."""
    expected = flatten(template, prefix)
    out, problems = [], []
    for name, leaf in expected.items():
        if name not in arrays:
            problems.append(f"{name}: missing from checkpoint")
            continue
        value = np.asarray(arrays[name])
        if value.shape != np.shape(leaf):
            problems.append(f"{name}: shape {value.shape} in checkpoint, {np.shape(leaf)} in model")
        out.append(value)
    extra = sorted(k for k in arrays if k.startswith(prefix + ".") and k not in expected)
    problems += [f"{k}: in checkpoint, not in model" for k in extra[:5]]
    if problems:
        raise CheckpointError(
            f"checkpoint {where} does not fit the model:\n  " + "\n  ".join(problems[:20])
        )
    return jax.tree_util.tree_unflatten(jax.tree_util.tree_structure(template), out)


def _orbax() -> Any:
    """orbax.checkpoint, imported on first use: reading an export (every evaluation) needs
    only `unflatten`, and orbax takes a third of a second to import."""
    import orbax.checkpoint as ocp

    return ocp


class Checkpoints:
    """The checkpoints of one run directory, keeping the newest `keep`."""

    def __init__(self, directory: str | Path, keep: int = 2, create: bool = True):
        self.directory = Path(directory).absolute()
        if not create and not self.directory.is_dir():
            raise CheckpointError(f"no checkpoint directory at {self.directory}")
        ocp = _orbax()
        self.manager = ocp.CheckpointManager(
            self.directory,
            options=ocp.CheckpointManagerOptions(
                max_to_keep=keep, create=create, enable_async_checkpointing=False
            ),
            item_names=("arrays", "meta"),
        )

    def latest_step(self) -> int | None:
        return self.manager.latest_step()

    def save(self, step: int, trees: dict[str, Any], meta: dict[str, Any]) -> None:
        """Save named pytrees (e.g. params, opt_state) and JSON metadata at `step`."""
        arrays = {}
        for name, tree in trees.items():
            arrays.update({k: np.asarray(v) for k, v in flatten(tree, name).items()})
        args = _orbax().args
        self.manager.save(
            step,
            args=args.Composite(
                arrays=args.StandardSave(arrays), meta=args.JsonSave({**meta, "step": step})
            ),
            force=True,
        )
        self.manager.wait_until_finished()

    def meta(self, step: int | None = None) -> dict[str, Any]:
        step = self._step(step)
        args = _orbax().args
        return self.manager.restore(step, args=args.Composite(meta=args.JsonRestore())).meta

    def check(self, expect: dict[str, Any], step: int | None = None) -> dict[str, Any]:
        """The checkpoint's metadata; CheckpointError listing every field that differs from `expect`."""
        step = self._step(step)
        meta = self.meta(step)
        problems = diff({k: meta.get(k, "<missing>") for k in expect}, expect)
        if problems:
            where = self.directory / str(step)
            raise CheckpointError(
                f"checkpoint {where} is incompatible:\n  " + "\n  ".join(problems)
            )
        return meta

    def restore(
        self, templates: dict[str, Any], expect: dict[str, Any], step: int | None = None
    ) -> tuple[dict[str, Any], dict[str, Any]]:
        """Restore the pytrees named in `templates` (same structure as saved).

        `expect` holds metadata that must match (e.g. {"kind": ..., "model": config});
        any difference raises CheckpointError listing the fields."""
        step = self._step(step)
        meta = self.check(expect, step)
        args = _orbax().args
        arrays = self.manager.restore(
            step, args=args.Composite(arrays=args.StandardRestore())
        ).arrays
        where = self.directory / str(step)
        return {name: unflatten(t, arrays, name, where) for name, t in templates.items()}, meta

    def _step(self, step: int | None) -> int:
        step = self.latest_step() if step is None else step
        if step is None:
            raise CheckpointError(f"no checkpoint found in {self.directory}")
        return step


def read_meta(run: str | Path) -> dict[str, Any]:
    """Metadata of a run directory's latest checkpoint (CheckpointError if none)."""
    return Checkpoints(Path(run) / "checkpoints", create=False).meta()


def load_params(run: str | Path, model: nnx.Module, expect: dict[str, Any]) -> nnx.Module:
    """`model` with the latest params of a run directory (for inference; no optimiser state)."""
    graphdef, params = nnx.split(model)
    trees, _ = Checkpoints(Path(run) / "checkpoints", create=False).restore(
        {"params": params}, expect
    )
    return nnx.merge(graphdef, trees["params"])
