"""`KeyActions`, the one value a policy returns, in a module that imports neither JAX nor
MuJoCo: a policy (or a client of a served one) builds it from numpy arrays without loading
the simulator.  A NamedTuple, so JAX maps over it as a pytree with no registration (a
None field is an empty subtree)."""

from __future__ import annotations

from typing import Any, NamedTuple


class KeyActions(NamedTuple):
    """Key actions with a leading axis: one per world of a batch (B, ...) when a policy
    acts, or a padded list for one world (K, ...) when an expert plans.  Tip position
    (., 3), quaternion (., 4, wxyz), gripper open amount (.,) in [0, 1], validity (.,).
    Each field is a numpy or JAX array.  A policy's answer may say why a world gets no
    action: `end_reason` (B,) int Outcome codes (bad LLM output, a server's error; 0: none,
    the world ends as no_action), read where valid is False.  The evaluator takes it off
    before the physics, which never sees it (None there)."""

    pos: Any
    quat: Any
    gripper: Any
    valid: Any
    end_reason: Any = None
