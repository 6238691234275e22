"""Policies for the evaluator: the contract and the built-in ones.

See `agnostos_mjx.policies.base` for the contract (`Policy`, the `Round` a policy sees);
`make_policy("oracle")` or `make_policy("my_module:MyPolicy")` builds one."""

from __future__ import annotations

from agnostos_mjx.policies.base import (
    Policy,
    PrivilegedAccessError,
    Round,
    list_policies,
    load_object,
    make_policy,
    no_actions,
    register_policy,
)

__all__ = ["Policy", "PrivilegedAccessError", "Round", "list_policies", "load_object",
           "make_policy", "no_actions", "register_policy"]
