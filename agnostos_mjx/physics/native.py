"""Native MuJoCo on CPU threads via `mujoco.rollout`: the CPU default."""

from __future__ import annotations

import copy
import threading

import mujoco
import numpy as np
from mujoco import rollout

from agnostos_mjx.infra.settings import usable_cores
from agnostos_mjx.physics.base import PhysicsState, check_steps
from agnostos_mjx.physics.capabilities import CAPABILITIES

_STATE_FIELDS = {
    mujoco.mjtState.mjSTATE_TIME: "time",
    mujoco.mjtState.mjSTATE_QPOS: "qpos",
    mujoco.mjtState.mjSTATE_QVEL: "qvel",
    mujoco.mjtState.mjSTATE_ACT: "act",
}
# Mocap poses and active equalities are not part of mjSTATE_FULLPHYSICS; rollout
# takes them per step as part of the "control" vector instead.
_CONTROL_FIELDS = {
    mujoco.mjtState.mjSTATE_CTRL: "ctrl",
    mujoco.mjtState.mjSTATE_MOCAP_POS: "mocap_pos",
    mujoco.mjtState.mjSTATE_MOCAP_QUAT: "mocap_quat",
    mujoco.mjtState.mjSTATE_EQ_ACTIVE: "eq_active",
}
STATE_SPEC = mujoco.mjtState.mjSTATE_FULLPHYSICS
CONTROL_SPEC = sum(int(b) for b in _CONTROL_FIELDS)


def _layout(model: mujoco.MjModel, spec: int, fields: dict) -> tuple[int, dict[str, slice]]:
    """Offsets of named components inside an mj_getState vector of `spec`."""
    slices, offset = {}, 0
    for bit in sorted(mujoco.mjtState.__members__.values(), key=int):
        if int(bit) & (int(bit) - 1) or not int(bit) & int(spec):
            continue
        size = mujoco.mj_stateSize(model, bit)
        if bit in fields:
            slices[fields[bit]] = slice(offset, offset + size)
        offset += size
    assert offset == mujoco.mj_stateSize(model, spec)
    return offset, slices


# One rollout at a time on the process's persistent thread pool (it already uses every
# core): tasks running at once on threads (evaluation/rollout.py) take turns here while the
# rest of their key actions (conditions, planner) and the policy overlap.  A pool per task
# instead oversubscribed the cores: the main job ran far slower with 8
# processes x 3 tasks (docs/performance.md).
_POOL_LOCK = threading.Lock()


class NativeBackend:
    name = "native"
    capabilities = CAPABILITIES["native"]

    def __init__(self, model: mujoco.MjModel, nthread: int | None = None):
        self.model = model
        self.nthread = nthread or usable_cores()
        self._datas = [mujoco.MjData(model) for _ in range(self.nthread)]
        self._models: list[mujoco.MjModel] = []
        self.nstate, self._state_slices = _layout(model, STATE_SPEC, _STATE_FIELDS)
        self.ncontrol, self._control_slices = _layout(model, CONTROL_SPEC, _CONTROL_FIELDS)

    def _pack_state(self, state: PhysicsState) -> np.ndarray:
        out = np.zeros((state.batch, self.nstate))
        for name, sl in self._state_slices.items():
            out[:, sl] = np.asarray(getattr(state, name), np.float64).reshape(state.batch, -1)
        return out

    def _pack_control(self, state: PhysicsState, ctrl: np.ndarray) -> np.ndarray:
        b, t = ctrl.shape[:2]
        out = np.zeros((b, t, self.ncontrol))
        for name, sl in self._control_slices.items():
            value = ctrl if name == "ctrl" else np.asarray(getattr(state, name), np.float64)
            out[..., sl] = value.reshape(b, -1 if name == "ctrl" else 1, sl.stop - sl.start)
        return out

    def _world_models(self, eq_data: np.ndarray) -> list[mujoco.MjModel]:
        """One model per world, since grasp welds carry per-world data."""
        while len(self._models) < len(eq_data):
            self._models.append(copy.copy(self.model))
        models = self._models[: len(eq_data)]
        for m, data in zip(models, eq_data):
            m.eq_data[:] = data
        return models

    def run(self, state: PhysicsState, ctrl: np.ndarray, steps: np.ndarray | None = None
            ) -> tuple[PhysicsState, np.ndarray]:
        """See Backend.run.  Worlds with equal step counts run as one rollout (a few groups:
        step counts come from control.STEP_BUCKETS); frozen worlds cost nothing here."""
        state, sens, _ = self.run_with_qpos(state, ctrl, steps)
        return state, sens

    def run_with_qpos(self, state: PhysicsState, ctrl: np.ndarray,
                      steps: np.ndarray | None = None
                      ) -> tuple[PhysicsState, np.ndarray, np.ndarray]:
        """`run`, plus qpos (B, T, nq) after each step, for rendering intermediate frames
        (the rollout computes every step's state anyway: no extra physics).  Rows past a
        world's end repeat its last row, as sensordata's; a world with 0 steps has its
        current qpos in every row."""
        state = state.numpy()
        b, t = ctrl.shape[:2]
        steps = check_steps(steps, b, t)
        if np.all(steps == t):
            return self._rollout(state, ctrl)
        sens = np.zeros((b, t, self.model.nsensordata))
        qpos = np.repeat(np.asarray(state.qpos, np.float64)[:, None], t, axis=1)
        out = state
        for n in np.unique(steps[steps > 0]):
            idx = np.nonzero(steps == n)[0]
            part, s, q = self._rollout(state.rows(idx), ctrl[idx, :n])
            out = out.with_rows(idx, part)
            sens[idx, :n] = s
            sens[idx, n:] = s[:, -1:]
            qpos[idx, :n] = q
            qpos[idx, n:] = q[:, -1:]
        return out, sens, qpos

    def _rollout(self, state: PhysicsState, ctrl: np.ndarray
                 ) -> tuple[PhysicsState, np.ndarray, np.ndarray]:
        ctrl = np.asarray(ctrl, np.float64)
        if self.model.neq and np.any(state.eq_data != self.model.eq_data):
            models = self._world_models(state.eq_data)
        else:
            models = self.model
        with _POOL_LOCK:
            states, sensordata = rollout.rollout(
                models, self._datas, self._pack_state(state), self._pack_control(state, ctrl),
                control_spec=CONTROL_SPEC, persistent_pool=True,
            )
        last = states[:, -1]
        fields = {
            name: last[:, sl].reshape(np.shape(getattr(state, name)))
            for name, sl in self._state_slices.items()
        }
        qpos = states[..., self._state_slices["qpos"]]
        return state.replace(ctrl=ctrl[:, -1], **fields), sensordata, qpos
