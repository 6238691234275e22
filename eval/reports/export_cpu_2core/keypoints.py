"""PerAct's keypoint_discovery on dense episodes: 1 demo per task exported with
``--every rlbench`` (front camera, 32 px: the images do not matter here), then per key
action the keypoint nearest its keyframe among the action's own frames, its distance to the
keyframe's gripper pose (mm, deg) and whether the gripper state matches.

    PYTHONPATH=.:tests python eval/reports/export_cpu_2core/keypoints.py \
        /tmp/dense_all seen
"""

import json
import sys
import time
from pathlib import Path

import numpy as np
from test_export import keypoint_discovery  # PerAct's, copied unchanged (see tests/test_export.py)

from agnostos_mjx.data import export as ex
from agnostos_mjx.infra.settings import configure_jax
from agnostos_mjx.tasks import parse_tasks

configure_jax()  # as the commands do, before JAX starts

out = Path(sys.argv[1])
rows = {}
for task in [t.name for t in parse_tasks(sys.argv[2])]:
    t0 = time.time()
    ex.export(ex.ExportConfig(out=out, tasks=(task,), demos=1, cameras=("front",), size=32,
                              batch=1, every="rlbench"))
    ep = ex.read_episode(ex.episode_dir(out, task, 0), verify=False)
    demo, keys = ep["demo"], ep["keyframes"]
    kp = keypoint_discovery(demo)
    pose, grip = ep["low_dim"]["gripper_pose"], ep["low_dim"]["gripper_open"]
    per = []
    for lo, hi in zip(keys[:-1], keys[1:]):
        inside = [k for k in kp if lo < k <= hi]
        if not inside:
            per.append((hi, None))
            continue
        k = min(inside, key=lambda k: abs(k - hi))
        mm = float(np.linalg.norm(pose[k, :3] - pose[hi, :3]) * 1000)
        deg = float(np.degrees(2 * np.arccos(min(1.0, abs(np.dot(pose[k, 3:], pose[hi, 3:]))))))
        per.append((hi, k, round(mm, 1), round(deg, 2), bool(grip[k] == grip[hi])))
    rows[task] = dict(frames=len(demo), keyframes=keys, keypoints=kp,
                      exact=sum(k in kp for k in keys[1:]), per=per)
    print(task, len(demo), "exact", rows[task]["exact"], "/", len(keys) - 1, "per", per,
          round(time.time() - t0, 1), flush=True)
(out / "keypoints.json").write_text(json.dumps(rows, indent=1))
