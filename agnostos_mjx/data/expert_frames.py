"""Running the experts with observations: per world the scene after reset and after each
key action (the keyframes), and with ``every`` the scene every K physics steps in between
(dense frames, as RLBench stores them); each frame an RLBenchObservation.world dict plus
the task's ``task_low_dim_state``."""

from __future__ import annotations

import logging

import numpy as np

log = logging.getLogger("agnostos_mjx.data.export")
RLBENCH_FRAME_PERIOD = 0.05  # s: RLBench stores every simulation step (50 ms, 20 Hz)


def frame_every(every: int | str | None, dt: float) -> int | None:
    """``--every`` -> physics steps between dense frames: None (keyframes only), a positive
    number of steps, or ``"rlbench"``: RLBench's frame period (50 ms, 20 Hz) at timestep
    `dt` (10 steps at our 5 ms)."""
    if every is None:
        return None
    if every == "rlbench":
        steps = max(1, round(RLBENCH_FRAME_PERIOD / dt))
        if abs(steps * dt - RLBENCH_FRAME_PERIOD) > 1e-9:
            log.warning("timestep %g s: frames every %d steps (%g s), not RLBench's %g s",
                        dt, steps, steps * dt, RLBENCH_FRAME_PERIOD)
        return steps
    steps = int(every)
    if steps < 1:
        raise ValueError(f"--every: a positive number of physics steps or 'rlbench', got {every!r}")
    return steps


def keyframe_observations(episodes, env, spec) -> tuple[object, list[list[dict]]]:
    """Run the expert; per world the observation after reset and after each key action."""
    env, frames, _ = episode_observations(episodes, env, spec)
    return env, frames


def episode_observations(episodes, env, spec, every: int | None = None
                         ) -> tuple[object, list[list[dict]], list[list[int]]]:
    """Run the expert; per world its frames (RLBenchObservation.world dicts plus
    ``task_low_dim_state``) and the indices of its keyframes among them (`expert_frames`)."""
    task = episodes.scene.task

    def snapshot(view) -> list[dict]:
        obs = episodes.observe(view, spec)
        state = task_low_dim_state(task, view.obs)
        return [{**obs.world(i), "task_low_dim_state": state[i]}
                for i in range(len(view.variation))]

    return expert_frames(episodes, env, snapshot, every)


def proprio_frames(episodes, env, every: int | None = None
                   ) -> tuple[object, list[list[dict]], list[list[int]]]:
    """`expert_frames` without rendering: each frame the proprioception (gripper_pose,
    gripper_open, joints) an export's frame holds; what a dense replay needs."""

    def snapshot(view) -> list[dict]:
        proprio = episodes.observer.proprioception(view)
        return [{k: v[i] for k, v in proprio.items()} for i in range(len(view.variation))]

    return expert_frames(episodes, env, snapshot, every, qpos=False)


def expert_frames(episodes, env, snapshot, every: int | None = None, qpos: bool = True
                  ) -> tuple[object, list[list[dict]], list[list[int]]]:
    """Run the expert; per world its frames (`snapshot(view)`: a dict per row of an
    EnvState `view`) and the indices of its keyframes among them.

    Keyframes: the scene after reset and after each key action.  With `every` = K (physics
    steps, recorded on the host) also the scene after every K-th physics step of each key
    action, counted from the action's start over its arm and gripper phases, before the
    action's keyframe (a step that ends the action is its keyframe, not repeated): a key
    action of S steps gives ceil(S / K) frames, the last its keyframe.  A dense frame is the
    physics state of that step (qpos when `qpos`, for rendering; the step's sensordata:
    joint velocities, gripper, object poses), painted with the state colours as the runtime
    would paint them had the phase ended there."""
    import jax

    from agnostos_mjx.sim.observables import Observation

    n = len(env.variation)
    frames: list[list[dict]] = [[] for _ in range(n)]
    keyframes: list[list[int]] = [[] for _ in range(n)]
    layout = episodes.scene.layout

    def snap(view, worlds, key: bool, rows=None):
        """Snapshot `view` and append its row rows[i] (default: worlds[i]) to world
        worlds[i]'s frames."""
        shots = snapshot(view)
        for i, w in enumerate(worlds):
            row = int(w) if rows is None else int(rows[i])
            if key:
                keyframes[w].append(len(frames[w]))
            frames[w].append(shots[row])

    def dense(env, results, rgba, running):
        """The in-between frames of one key action from its phases' StepResults."""
        colours = episodes.fns.colors
        offset = np.zeros(n, np.int64)  # steps of this action before the phase
        total = sum(r.valid.sum(1) for r in results)
        for r in results:
            steps = r.valid.sum(1)
            s = offset[:, None] + np.arange(r.valid.shape[1])[None] + 1
            want = r.valid & running[:, None] & (s % every == 0) & (s < total[:, None])
            for t in np.nonzero(want.any(0))[0]:
                rows = np.nonzero(want[:, t])[0]
                obs_t = Observation(r.sensordata[:, t], layout, r.attached[:, t])
                painted = colours.update(rgba, env.initial_obs, obs_t, env.variation)
                physics = env.physics.rows(rows)
                view = env.replace(
                    physics=physics if r.qpos is None else physics.replace(qpos=r.qpos[rows, t]),
                    data=r.sensordata[rows, t], attached=r.attached[rows, t],
                    geom_rgba=np.asarray(painted)[rows], variation=env.variation[rows],
                    initial_data=env.initial_data[rows])
                snap(view, rows, key=False, rows=range(len(rows)))
            # The colours after the phase, as the key action paints them.
            last = np.maximum(steps - 1, 0)
            obs_end = Observation(r.sensordata[np.arange(n), last], layout,
                                  r.attached[np.arange(n), last])
            rgba = colours.update(rgba, env.initial_obs, obs_end, env.variation)
            offset += steps

    snap(env, range(n), key=True)
    actions = episodes.expert_actions(env)
    recording = episodes.record_qpos
    episodes.record_qpos = every is not None and qpos
    try:
        for k in range(actions.pos.shape[1]):
            step = jax.tree.map(lambda x, k=k: x[:, k], actions)
            running = ~env.done & np.asarray(step.valid, bool)
            if not running.any():
                break
            rgba = env.geom_rgba
            env, results = episodes.step(env, step, record=every is not None)
            if every is not None and results:
                dense(env, results, rgba, running)
            snap(env, np.nonzero(running)[0], key=True)
    finally:
        episodes.record_qpos = recording
    return env, frames, keyframes


def next_frame_actions(frames: list[dict]) -> tuple[np.ndarray, np.ndarray]:
    """The dense actions of one demo's frames, as the LeRobot export writes them: frame t's
    action is frame t+1's gripper pose (x y z qx qy qz qw, float64 of the float32 pose) and
    gripper_open, the last frame's its own.  Returns (target pose (n, 7), gripper (n,))."""
    pose = np.stack([np.asarray(f["gripper_pose"], np.float32) for f in frames])
    grip = np.array([f["gripper_open"] for f in frames], np.float32)
    return (np.concatenate([pose[1:], pose[-1:]]).astype(np.float64),
            np.concatenate([grip[1:], grip[-1:]]))


def task_low_dim_state(task, obs) -> np.ndarray:
    """(B, n) RLBench-style ``task_low_dim_state``: the pose (x y z qx qy qz qw) of each of
    the task's observed frames (``task.observed_frames`` order), then its joint positions
    (``task.joints``), as RLBench's ``Task.get_low_dim_state`` lists its objects' poses and
    joint positions."""
    parts = []
    for frame in task.observed_frames:
        quat = np.asarray(obs.quat(frame), np.float64)
        parts += [np.asarray(obs.pos(frame), np.float64), quat[..., [1, 2, 3, 0]]]
    parts += [np.asarray(obs.joint(j), np.float64)[..., None] for j in task.joints]
    batch = np.asarray(obs.data).shape[0]
    return np.concatenate(parts, -1) if parts else np.zeros((batch, 0))
