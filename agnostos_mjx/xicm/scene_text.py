"""X-ICM's text view of a live scene: named objects -> voxel indices -> strings.

The original averages segmented point clouds over five cameras; by default we read
the ground-truth frame position of each named object (a documented difference), so the
text is exact and costs nothing to compute.  `segmented_object_voxels` computes it as the
original does, from rendered segmentation and point clouds (observation.py).
"""

from __future__ import annotations

import numpy as np

from agnostos_mjx.sim.observables import Observation
from agnostos_mjx.sim.textualise import format_query, point_to_voxel
from agnostos_mjx.tasks.base import Task


def object_voxels(task: Task, obs: Observation) -> list[dict[str, list[int]]]:
    """Per world, {display name: [x, y, z] voxel index} in the task's declared order."""
    names = list(task.objects)
    if not names:
        return [{} for _ in range(np.shape(obs.data)[0])]
    positions = np.stack([np.asarray(obs.pos(task.objects[n])) for n in names], axis=-2)
    voxels = np.asarray(point_to_voxel(positions))
    return [{n: [int(v) for v in world[i]] for i, n in enumerate(names)} for world in voxels]


def segmented_object_voxels(observation, worlds=None) -> list[dict[str, list[int]]]:
    """Per world, X-ICM's object voxels from an RLBenchObservation with segmentation and
    point clouds (xicm_reference.md 3.4): the mean of an object's segmented points per
    camera, averaged over the cameras that see it; objects no camera sees are omitted.
    Objects keep the task's declared order (the original sorts by CoppeliaSim handle)."""
    from agnostos_mjx.runtime.observation import segmented_object_positions

    worlds = range(observation.batch) if worlds is None else worlds
    out = []
    for w in worlds:
        positions = segmented_object_positions(observation, int(w))
        out.append({n: [int(v) for v in np.asarray(point_to_voxel(p))]
                    for n, p in positions.items()})
    return out


def query_texts(task: Task, obs: Observation, variations, objects=None) -> list[str]:
    """The query line X-ICM appends to its prompt, one per world:
    `['instruction': <first description>, {<objects>}]>`; `objects` (per world, voxel
    dicts) replaces the ground-truth positions."""
    objects = object_voxels(task, obs) if objects is None else objects
    return [format_query(task.descriptions(int(v))[0], o) for v, o in zip(variations, objects)]
