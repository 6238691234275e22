"""Policies for the evaluator: the plug-in interface and the built-in ones.

See `agnostos_mjx.policies.base` for the interface; `make_policy("oracle")`
or `make_policy("my_module:MyPolicy")` builds one."""

from __future__ import annotations

from agnostos_mjx.policies.base import (
    Policy,
    PolicyAdapter,
    PolicyExtras,
    list_policies,
    load_object,
    make_policy,
    no_actions,
    register_policy,
)

__all__ = ["Policy", "PolicyAdapter", "PolicyExtras", "list_policies", "load_object",
           "make_policy", "no_actions", "register_policy"]
