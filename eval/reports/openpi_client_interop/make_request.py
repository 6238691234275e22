"""Our side: one real request (lamp_on, seed 0, episode 0, first step) for openpi_call.py."""

import numpy as np

from agnostos_mjx.evaluation.protocol import episode_keys
from agnostos_mjx.remote import wire
from agnostos_mjx.remote.adapter import sim_state
from agnostos_mjx.runtime.env import Episodes
from agnostos_mjx.tasks import get_task

task = get_task("lamp_on")
runner = Episodes(task, "native")
env = runner.reset(episode_keys(np.array([0]), np.array([0])), np.array([0]))
request = {"sim_state": sim_state(runner, env, 0, 0), "prompt": task.descriptions(0)[0]}
open("/tmp/agnostos_request.msgpack", "wb").write(wire.packb(request))
plan = runner.expert_actions(env)
q = np.asarray(plan.quat)[0, 0]
print("in-process expert, first key action (x y z qx qy qz qw open):",
      np.concatenate([np.asarray(plan.pos)[0, 0], q[[1, 2, 3, 0]], np.asarray(plan.gripper)[0, :1]]))
