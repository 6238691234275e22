"""What an episode is: its scene key, variation and policy seed, the tasks and the groups.

The protocol follows X-ICM's evaluation (spec sections 6 and 9).  Episodes are
reproducible and independent of batching: episode `e` of seed `s` samples its scene from
``fold_in(PRNGKey(s), e)`` and, where the variation is sampled, its variation from
``fold_in(that key, 1)``.
"""

from __future__ import annotations

import functools
from collections.abc import Container, Sequence

import numpy as np

from agnostos_mjx.evaluation.config import EvalConfig, UsageError

VARIATION_STREAM = 1  # fold_in index of an episode key that draws its variation
# Aggregate groups as in X-ICM's gather_score.py; "All" is the unseen tasks
# (X-ICM's 23-task average).  Seen tasks get their own group.
GROUPS: tuple[tuple[str, frozenset[str]], ...] = (
    ("Level-1", frozenset({"unseen_level1"})),
    ("Level-2", frozenset({"unseen_level2"})),
    ("All", frozenset({"unseen_level1", "unseen_level2"})),
    ("Seen", frozenset({"seen"})),
)


def group_label(name: str) -> str:
    """How reports name a group (All covers the unseen tasks only)."""
    return "All (unseen)" if name == "All" else name


def episode_keys(seeds: np.ndarray, episodes: np.ndarray):
    """Scene keys ``fold_in(PRNGKey(seed), episode)``, shape (n, 2)."""
    return _episode_keys()(np.asarray(seeds, np.uint32), np.asarray(episodes, np.uint32))


@functools.cache
def _episode_keys():
    """One compiled program (per batch size), not one per random primitive."""
    import jax

    return jax.jit(jax.vmap(lambda s, e: jax.random.fold_in(jax.random.PRNGKey(s), e)))


def episode_variations(keys, num_variations: int, split: str, mode: str) -> np.ndarray:
    """Each episode's variation under `mode` (see --variations)."""
    import jax

    n = len(keys)
    if mode.isdigit():
        variation = int(mode)
        if variation >= num_variations:
            raise UsageError(f"variation {variation} out of range 0..{num_variations - 1}")
        return np.full(n, variation, np.int32)
    if mode == "zero" or (mode == "protocol" and split != "seen") or num_variations == 1:
        return np.zeros(n, np.int32)
    draw = lambda k: jax.random.randint(jax.random.fold_in(k, VARIATION_STREAM), (), 0,
                                        num_variations)
    return np.asarray(jax.vmap(draw)(keys), np.int32)


def policy_seed(seed: int, episode: int) -> int:
    """The seed of a policy's own randomness in an episode (X-ICM's random demo selection):
    like the scene, a function of (seed, episode) alone, whatever batch the episode is in."""
    return int(seed) * 100_003 + int(episode)


def select_tasks(cfg: EvalConfig) -> list[str]:
    """The names of the tasks --tasks names, checked against --variations (all of them: a
    multi-process run reports the same usage errors in every process).  Their modules are
    imported only where --variations needs their variation counts."""
    from agnostos_mjx.tasks import get_task, parse_task_names

    try:
        names = parse_task_names(cfg.protocol.tasks)
    except KeyError as e:
        raise UsageError(e.args[0] if e.args else str(e)) from None
    if not names:
        raise UsageError(f"--tasks {cfg.protocol.tasks!r} selects no registered task")
    if (variation := cfg.protocol.variations).isdigit():
        for t in map(get_task, names):
            if int(variation) >= t.num_variations:
                raise UsageError(f"--variations {variation}: {t.name} has variations "
                                 f"0..{t.num_variations - 1}")
    return names


def process_share(tasks: Sequence[str], cfg: EvalConfig) -> list[str]:
    """The tasks this process runs: every N-th from its index (all when one process)."""
    return list(tasks[cfg.run.process_id::cfg.run.num_processes])


def pending_episodes(task: str, cfg: EvalConfig, recorded: Container[tuple[str, int, int]]
                     ) -> list[tuple[int, int]]:
    """The (seed, episode) pairs of `task` still to run: all but the `recorded` ones."""
    return [(s, e) for s in cfg.protocol.seeds for e in range(cfg.protocol.episodes)
            if (task, s, e) not in recorded]
