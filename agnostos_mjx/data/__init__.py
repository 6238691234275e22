"""Seen-task demonstration bank: generation (`python -m agnostos_mjx.data.generate`),
storage and the loader policies and the dynamics model read from."""

from agnostos_mjx.data.bank import BankError, Demo, DemoBank

__all__ = ["BankError", "Demo", "DemoBank"]
