"""Shared pytest setup for agnostos_mjx (the `slow` marker is registered in pyproject.toml)."""
