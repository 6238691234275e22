"""X-ICM's text view of a live scene: named objects -> voxel indices -> strings.

The original averages segmented point clouds over five cameras; we read the
ground-truth frame position of each named object (a documented difference),
so the text is exact and costs nothing to compute.
"""

from __future__ import annotations

import numpy as np

from agnostos_mjx.observables import Observation
from agnostos_mjx.tasks.base import Task
from agnostos_mjx.textualise import format_query, point_to_voxel


def object_voxels(task: Task, obs: Observation) -> list[dict[str, list[int]]]:
    """Per world, {display name: [x, y, z] voxel index} in the task's declared order."""
    names = list(task.objects)
    if not names:
        return [{} for _ in range(np.shape(obs.data)[0])]
    positions = np.stack([np.asarray(obs.pos(task.objects[n])) for n in names], axis=-2)
    voxels = np.asarray(point_to_voxel(positions))
    return [{n: [int(v) for v in world[i]] for i, n in enumerate(names)} for world in voxels]


def query_texts(task: Task, obs: Observation, variations) -> list[str]:
    """The query line X-ICM appends to its prompt, one per world:
    `['instruction': <first description>, {<objects>}]>`."""
    return [
        format_query(task.descriptions(int(v))[0], objects)
        for v, objects in zip(variations, object_voxels(task, obs))
    ]
