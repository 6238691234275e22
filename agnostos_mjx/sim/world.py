"""Scene assembly: RLBench world + Panda + one task, compiled to an MjModel.

`SceneBuilder` is what task builders write into (a thin layer over MjSpec that
also records observed frames and initial joint values).  `build_scene(task)`
adds the sensors every observable needs and returns a frozen `SceneModel`,
the static description shared by the physics backends, control and tasks.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Protocol

import jax
import mujoco
import numpy as np

from agnostos_mjx.sim.observables import Layout


class SceneTask(Protocol):
    """What building a scene reads of a task (tasks.base.Task has it all)."""

    name: str
    joints: tuple[str, ...]
    graspables: tuple[str, ...]

    @property
    def observed_frames(self) -> tuple[str, ...]: ...

    def build(self, scene: Any) -> None: ...


@jax.tree_util.register_dataclass
@dataclass
class Placement:
    """What a sampler returns: world poses of mocap bodies, joint positions,
    and geom colours, all keyed by MJCF name (static keys, traced values)."""

    bodies: dict[str, tuple[Any, Any]] = field(default_factory=dict)
    joints: dict[str, Any] = field(default_factory=dict)
    colors: dict[str, Any] = field(default_factory=dict)

ARM_JOINTS = tuple(f"joint{i}" for i in range(1, 8))
# Home configuration: the one nearest RLBench's recorded start joints
# [0, 0.175, 0, -0.873, 0, 1.222, 0.785] that puts the tip exactly at RLBench's
# recorded start pose (0.2785, -0.0082, 1.4719), quat xyzw (0, 0.9927, 0, 0.1209);
# the recorded joints alone miss it by 2 cm and 4 degrees.
HOME_QPOS = (-0.003, 0.1413, -0.0019, -0.8802, 0.0015, 1.2637, 0.7812)
FINGER_OPEN = 0.04

# Collision classes (contype, conaffinity): robot collision geoms are (1, 0),
# the table (4, 3); task objects collide with the robot, each other and the table.
OBJECT_COLLISION = (2, 3)
VISUAL_ONLY = (0, 0)


def scenes_dir() -> Path:
    """MJCF folder: packaged copy when installed as a wheel, else the repo's `scenes/`."""
    packaged = Path(__file__).parents[1] / "_scenes"
    return packaged if packaged.is_dir() else Path(__file__).resolve().parents[2] / "scenes"


class SceneBuilder:
    """What a task's `build` writes into: the MjSpec plus bookkeeping."""

    def __init__(self, spec: mujoco.MjSpec):
        self.spec = spec
        self.initial_joints: dict[str, float] = {}

    @property
    def world(self) -> mujoco.MjsBody:
        return self.spec.worldbody

    def mocap(self, name: str) -> mujoco.MjsBody:
        """A static body whose world pose the sampler sets every episode."""
        return self.spec.worldbody.add_body(name=name, mocap=True)

    def exclude(self, body1: str, body2: str) -> None:
        self.spec.add_exclude(bodyname1=body1, bodyname2=body2)


@dataclass(frozen=True, eq=False)
class SceneModel:
    """Static description of one task's compiled scene."""

    task: SceneTask
    model: mujoco.MjModel
    layout: Layout
    mocap_index: dict[str, int]  # mocap body name -> row in mocap_pos
    qpos_address: dict[str, int]  # joint name -> qpos address (1-dof joints)
    free_address: dict[str, int]  # body name -> qpos address of its free joint
    weld_ids: tuple[int, ...]  # weld equality per graspable (inactive at start)
    graspable_bodies: tuple[int, ...]
    hand_body: int
    initial_qpos: np.ndarray
    initial_mocap_pos: np.ndarray
    initial_mocap_quat: np.ndarray

    @property
    def arm_qpos(self) -> np.ndarray:
        return np.array([self.qpos_address[j] for j in ARM_JOINTS])


def _add_sensors(spec: mujoco.MjSpec, task: SceneTask) -> Layout:
    entries: list[tuple[str, int, int]] = []
    offset = 0

    def add(name: str, sensor_type, obj_type, obj_name: str, dim: int) -> None:
        nonlocal offset
        spec.add_sensor(name=name, type=sensor_type, objtype=obj_type, objname=obj_name)
        entries.append((name, offset, dim))
        offset += dim

    def add_group(name: str, sensor_type, joints: tuple[str, ...]) -> None:
        nonlocal offset
        for j in joints:
            spec.add_sensor(name=f"{name}:{j}", type=sensor_type,
                            objtype=mujoco.mjtObj.mjOBJ_JOINT, objname=j)
        entries.append((name, offset, len(joints)))
        offset += len(joints)

    S, O = mujoco.mjtSensor, mujoco.mjtObj  # noqa: E741
    add_group("arm_q", S.mjSENS_JOINTPOS, ARM_JOINTS)
    add_group("arm_qd", S.mjSENS_JOINTVEL, ARM_JOINTS)
    add("finger_q", S.mjSENS_JOINTPOS, O.mjOBJ_JOINT, "finger_left", 1)
    add("tip.pos", S.mjSENS_FRAMEPOS, O.mjOBJ_SITE, "tip", 3)
    add("tip.quat", S.mjSENS_FRAMEQUAT, O.mjOBJ_SITE, "tip", 4)
    for frame in task.observed_frames:
        # Bodies are observed through their frame (XBODY), not their inertial frame.
        obj = O.mjOBJ_SITE if spec.site(frame) is not None else O.mjOBJ_XBODY
        if obj == O.mjOBJ_XBODY and spec.body(frame) is None:
            raise ValueError(f"task {task.name}: observed frame {frame!r} is neither site nor body")
        add(f"{frame}.pos", S.mjSENS_FRAMEPOS, obj, frame, 3)
        add(f"{frame}.quat", S.mjSENS_FRAMEQUAT, obj, frame, 4)
    for joint in task.joints:
        add(f"{joint}.q", S.mjSENS_JOINTPOS, O.mjOBJ_JOINT, joint, 1)
    return Layout(tuple(entries))


@functools.cache
def build_scene(task: SceneTask) -> SceneModel:
    """Compile the world, the robot and `task` into one model (cached per task)."""
    spec = mujoco.MjSpec.from_file(str(scenes_dir() / "world.xml"))
    builder = SceneBuilder(spec)
    task.build(builder)
    for body in task.graspables:
        spec.add_equality(type=mujoco.mjtEq.mjEQ_WELD, name=f"grasp_{body}", name1="hand",
                          name2=body, objtype=mujoco.mjtObj.mjOBJ_BODY, active=False,
                          solref=[0.005, 1.0])
    layout = _add_sensors(spec, task)
    # Geoms fixed to the world or to a mocap body never touch each other in C
    # MuJoCo, but MJX-jax would collide them (a sunk button base with the
    # table): exclude such body pairs explicitly so all backends agree.
    probe = spec.compile()
    weld = probe.body_weldid
    static = [probe.body(b).name for b in range(1, probe.nbody)
              if weld[b] == 0 or probe.body_mocapid[weld[b]] >= 0]
    for name in static:
        spec.add_exclude(bodyname1="world", bodyname2=name)
    model = spec.compile()

    qpos_address = {}
    for j in range(model.njnt):
        if int(model.jnt_type[j]) in (int(mujoco.mjtJoint.mjJNT_HINGE), int(mujoco.mjtJoint.mjJNT_SLIDE)):
            qpos_address[model.joint(j).name] = int(model.jnt_qposadr[j])
    free_address = {
        model.body(int(model.jnt_bodyid[j])).name: int(model.jnt_qposadr[j])
        for j in range(model.njnt)
        if int(model.jnt_type[j]) == int(mujoco.mjtJoint.mjJNT_FREE)
    }
    mocap_index = {
        model.body(b).name: int(model.body_mocapid[b])
        for b in range(model.nbody)
        if model.body_mocapid[b] >= 0
    }
    qpos = model.qpos0.copy()
    for name, value in zip(ARM_JOINTS, HOME_QPOS):
        qpos[qpos_address[name]] = value
    qpos[qpos_address["finger_left"]] = FINGER_OPEN
    qpos[qpos_address["finger_right"]] = FINGER_OPEN
    for name, value in builder.initial_joints.items():
        qpos[qpos_address[name]] = value
    data = mujoco.MjData(model)
    mujoco.mj_kinematics(model, data)
    mocap_pos = np.array([data.xpos[b] for b in range(model.nbody) if model.body_mocapid[b] >= 0])
    mocap_quat = np.array([data.xquat[b] for b in range(model.nbody) if model.body_mocapid[b] >= 0])
    return SceneModel(
        task=task,
        model=model,
        layout=layout,
        mocap_index=mocap_index,
        qpos_address=qpos_address,
        free_address=free_address,
        weld_ids=tuple(model.equality(f"grasp_{b}").id for b in task.graspables),
        graspable_bodies=tuple(model.body(b).id for b in task.graspables),
        hand_body=model.body("hand").id,
        initial_qpos=qpos,
        initial_mocap_pos=mocap_pos.reshape(-1, 3),
        initial_mocap_quat=mocap_quat.reshape(-1, 4),
    )


def apply_placement(scene: SceneModel, placement: Placement):
    """Placement (name-keyed, traced) -> (qpos, mocap_pos, mocap_quat, geom_rgba)."""
    import jax.numpy as jnp

    qpos = jnp.asarray(scene.initial_qpos, jnp.float32)
    for name, value in placement.joints.items():
        qpos = qpos.at[scene.qpos_address[name]].set(value)
    mocap_pos = jnp.asarray(scene.initial_mocap_pos, jnp.float32)
    mocap_quat = jnp.asarray(scene.initial_mocap_quat, jnp.float32)
    for name, (pos, quat) in placement.bodies.items():
        if name in scene.mocap_index:
            mocap_pos = mocap_pos.at[scene.mocap_index[name]].set(pos)
            mocap_quat = mocap_quat.at[scene.mocap_index[name]].set(quat)
        elif name in scene.free_address:
            adr = scene.free_address[name]
            qpos = qpos.at[adr : adr + 3].set(pos).at[adr + 3 : adr + 7].set(quat)
        else:
            raise KeyError(f"{scene.task.name}: placement body {name!r} is neither mocap nor free")
    geom_rgba = jnp.asarray(scene.model.geom_rgba, jnp.float32)
    for name, rgba in placement.colors.items():
        geom_rgba = geom_rgba.at[scene.model.geom(name).id, :3].set(rgba)
    return qpos, mocap_pos, mocap_quat, geom_rgba


def posed_data(model: mujoco.MjModel, physics, world: int) -> mujoco.MjData:
    """An MjData holding world `world` of a batched PhysicsState, kinematics computed:
    the frames of one world for host-side geometry (grasp welds, tests, inspection)."""
    data = mujoco.MjData(model)
    data.qpos[:] = physics.qpos[world]
    data.mocap_pos[:] = physics.mocap_pos[world]
    data.mocap_quat[:] = physics.mocap_quat[world]
    mujoco.mj_kinematics(model, data)
    return data
