"""`KeyActions`, the one value a policy returns, in a module that imports neither JAX nor
MuJoCo: a policy (or a client of a served one) builds it from numpy arrays without loading
the simulator.  A NamedTuple, so JAX maps over it as a pytree with no registration."""

from __future__ import annotations

from typing import Any, NamedTuple


class KeyActions(NamedTuple):
    """Key actions with a leading axis: one per world of a batch (B, ...) when a policy
    acts, or a padded list for one world (K, ...) when an expert plans.  Tip position
    (., 3), quaternion (., 4, wxyz), gripper open amount (.,) in [0, 1], validity (.,).
    Each field is a numpy or JAX array."""

    pos: Any
    quat: Any
    gripper: Any
    valid: Any
