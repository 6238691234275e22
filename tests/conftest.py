"""Shared pytest setup for agnostos_mjx (the `slow` marker is registered in pyproject.toml)."""

from __future__ import annotations

from pathlib import Path

import pytest

TASKS = ("open_drawer", "push_buttons")  # the tiny bank's seen tasks


def tiny_bank_config(out: Path, demos: int = 2):
    from agnostos_mjx.data.generate import GenerateConfig

    return GenerateConfig(out=out, tasks=TASKS, demos=demos, seed=3, backend="native",
                          batch=2, image_size=32, quiet=True)


@pytest.fixture(scope="session")
def bank_dir(tmp_path_factory) -> Path:
    """Two seen tasks x two demos at 32 x 32 pixels (about 20 s on 2 cores)."""
    from agnostos_mjx.data.generate import generate

    out = tmp_path_factory.mktemp("bank")
    generate(tiny_bank_config(out))
    return out
