"""Where a runner's IK and paths are computed: the numpy planner on the host (float64) or
the jitted one (float32, one program per robot shared by every task:
control.jit_for_robot), chosen once when the runner starts."""

from __future__ import annotations

import dataclasses
import functools
from collections.abc import Callable
from dataclasses import dataclass

import jax

from agnostos_mjx.sim import control
from agnostos_mjx.sim.control import PandaKinematics

PLANNERS = ("auto", "host", "device")


def resolve_planner(name: str) -> str:
    """`auto`: `device` when JAX has an accelerator, else `host`.  `device`: the jitted
    float32 planner (one program for every task, off the host's Python loop); `host`: numpy
    float64 (the CPU path, bit for bit as before).  The two can pick different IK
    solutions near a limit, so a run's records say which (`Episodes.planner`)."""
    if name not in PLANNERS:
        raise ValueError(f"unknown planner {name!r}; choose one of {', '.join(PLANNERS)}")
    if name == "auto":
        return "device" if jax.default_backend() != "cpu" else "host"
    return name


@dataclass(frozen=True)
class Planner:
    """One robot's planning calls, all of one kind (host or device) unless `chosen` mixes
    them: `plan(q, pos, quat) -> (path, duration, status)` (control.plan_arm),
    `reachable(q, pos, quat, valid)` (control.reachable), `dense_ik(q, pos, quat) ->
    (joint goal, status)` (control.dense_ik)."""

    plan: Callable
    reachable: Callable
    dense_ik: Callable
    on_device: bool  # whether `plan` and `reachable` are the jitted programs

    @classmethod
    def host(cls, kin: PandaKinematics) -> Planner:
        """numpy float64 on the caller's thread."""
        return cls(functools.partial(control.plan_arm, kin),
                   functools.partial(control.reachable, kin),
                   functools.partial(control.dense_ik, kin), on_device=False)

    @classmethod
    def device(cls, kin: PandaKinematics) -> Planner:
        """The jitted programs, one per robot in the process (compiled on first call)."""
        return cls(control.jit_for_robot(control.plan_arm, kin),
                   control.jit_for_robot(control.reachable, kin),
                   control.jit_for_robot(control.dense_ik, kin), on_device=True)

    @classmethod
    def chosen(cls, kin: PandaKinematics, asked: str) -> Planner:
        """The planner `--planner asked` gives next to host physics: plans and reachability
        where resolve_planner(asked) says; dense control's IK (one small descent per control
        step) on the host unless the device is asked for by name, since a device call's
        round trip costs more than the numpy IK."""
        base = cls.device(kin) if resolve_planner(asked) == "device" else cls.host(kin)
        dense = cls.device(kin) if asked == "device" else cls.host(kin)
        return dataclasses.replace(base, dense_ik=dense.dense_ik)
