"""Statistics for comparing evaluation runs: how sure can we be with 75 episodes a task?

A task's success rate comes from 3 seeds x 25 episodes, so a gap of ten points between two
models can be noise.  This module gives the few tools a reviewer expects, in pure numpy (scipy
is a test-only dependency):

* `wilson_interval`: a binomial confidence interval that stays inside [0, 1] and keeps its
  coverage near 0 % and 100 %, where most AGNOSTOS tasks sit (the normal "p +- 1.96 se"
  interval collapses to zero width there).
* `mcnemar_exact`: two runs on the *same* scenes (a scene depends only on task, seed and
  episode) are paired; only the episodes one run solved and the other did not carry
  information about which is better, and McNemar's exact test asks whether those discordant
  episodes split evenly.
* `bootstrap_difference` / `paired_bootstrap_difference`: a group's (Level-1, Level-2, ...)
  difference in success rate with a percentile interval, resampling episodes within each task
  (stratified, as the benchmark fixes the episodes per task).
* `pair_records`: which episodes of two runs pair up, and which do not.

Rates are fractions in [0, 1] here; the reports turn them into percent.
"""

from __future__ import annotations

import math
from collections.abc import Collection, Iterable, Mapping, Sequence
from dataclasses import dataclass, field

import numpy as np

Key = tuple[str, int, int]

# Above this many discordant pairs McNemar's tail is summed in log space: exact integer
# binomial coefficients grow to thousands of digits and the sum gets slow.
_EXACT_MAX_N = 2000


def wilson_interval(successes, n, z: float = 1.96):
    """Wilson score interval for a binomial proportion, as fractions ``(low, high)``.

    Chosen over the normal (Wald) interval because it has close to nominal coverage for small
    n and for rates near 0 or 1, and never leaves [0, 1].  Exact at the ends: 0 successes give
    low = 0, n successes give high = 1.  ``n = 0`` gives ``(0.0, 1.0)``: no episode, no
    information, every rate possible (rather than nan, which JSON cannot carry).

    Vectorised: `successes` and `n` may be arrays (broadcast); scalars in, floats out."""
    s = np.asarray(successes, dtype=np.float64)
    m = np.asarray(n, dtype=np.float64)
    if np.any(m < 0) or np.any(s < 0) or np.any(s > m):
        raise ValueError(f"need 0 <= successes <= n, got successes={successes}, n={n}")
    if z <= 0:
        raise ValueError(f"z must be positive, got {z}")
    s, m = np.broadcast_arrays(s, m)
    safe = np.where(m > 0, m, 1.0)
    p = s / safe
    z2 = z * z
    denom = 1.0 + z2 / safe
    centre = (p + z2 / (2.0 * safe)) / denom
    half = z * np.sqrt(p * (1.0 - p) / safe + z2 / (4.0 * safe * safe)) / denom
    low = np.where(s == 0, 0.0, np.clip(centre - half, 0.0, 1.0))
    high = np.where(s == m, 1.0, np.clip(centre + half, 0.0, 1.0))
    low = np.where(m == 0, 0.0, low)
    high = np.where(m == 0, 1.0, high)
    if low.ndim == 0:
        return float(low), float(high)
    return low, high


def _binom_half_tail(k: int, n: int) -> float:
    """P(X <= k) for X ~ Binomial(n, 1/2)."""
    if n <= _EXACT_MAX_N:
        # Integer arithmetic; int / int rounds correctly even for huge numerators.
        return sum(math.comb(n, i) for i in range(k + 1)) / (1 << n)
    # log C(n, i) by the running product C(n, i+1) = C(n, i) (n - i) / (i + 1), then
    # log-sum-exp: no overflow, relative error ~1e-12.
    i = np.arange(k, dtype=np.float64)
    log_terms = np.concatenate(([0.0], np.cumsum(np.log(n - i) - np.log(i + 1.0))))
    top = log_terms.max()
    return float(math.exp(top + math.log(np.exp(log_terms - top).sum()) - n * math.log(2.0)))


def mcnemar_exact(b: int, c: int) -> float:
    """Two-sided exact McNemar p-value from the discordant pair counts.

    `b`: pairs run A solved and run B did not; `c`: the reverse.  Concordant pairs say
    nothing about which run is better, so under "no difference" each discordant pair is a fair
    coin: p = 2 P(X <= min(b, c)), X ~ Binomial(b + c, 1/2), capped at 1 (the same value as
    scipy's ``binomtest(b, b + c, 0.5)``).  Exact rather than the chi-square approximation,
    which is poor for the handful of discordant episodes a task typically has.  ``b = c = 0``
    gives 1: no evidence either way."""
    b, c = int(b), int(c)
    if b < 0 or c < 0:
        raise ValueError(f"discordant counts must be >= 0, got b={b}, c={c}")
    n = b + c
    if n == 0 or b == c:
        return 1.0
    return min(1.0, 2.0 * _binom_half_tail(min(b, c), n))


def _as_outcomes(values: Iterable, name: str) -> np.ndarray:
    v = np.asarray(list(values) if not isinstance(values, np.ndarray) else values)
    if v.ndim != 1 or v.size == 0:
        raise ValueError(f"{name}: need a non-empty 1-D sequence of successes")
    return v.astype(bool)


def bootstrap_difference(a_by_task: Mapping[str, Sequence], b_by_task: Mapping[str, Sequence],
                         *, paired: bool | Collection[str] = True, n_boot: int = 10000,
                         seed: int = 0, level: float = 0.95) -> tuple[float, float, float]:
    """Success rate of run B minus run A over a group of tasks, with a percentile interval.

    `a_by_task` / `b_by_task`: task -> the per-episode successes (bools) of each run.  The
    group's rate is the mean over its tasks of each task's rate (all its episodes, seeds
    pooled): the benchmark's task-weighted average, which is the pooled rate of the group's
    episodes when every task has the same number of episodes (3 seeds x 25).

    Resampling is stratified: episodes are drawn with replacement *within* each task, keeping
    each task's episode count, because the protocol fixes the episodes per task (resampling
    tasks would ask another question: how a different task set would score).  A `paired` task
    (True: all; or a collection of task names) must hold the same episodes in the same order
    in both runs; its episodes are resampled as pairs, so the scene-to-scene variation both
    runs share cancels.  An unpaired task resamples each run on its own.  As outcomes are
    binary, a task's resample is drawn as counts (multinomial over the pair kinds, or one
    binomial per run), the same distribution as drawing episode indices but O(n_boot) memory.

    Returns ``(difference, low, high)`` as fractions: the observed difference and the
    `level` percentile interval.  Deterministic for a `seed`; identical paired runs give
    ``(0, 0, 0)``."""
    if set(a_by_task) != set(b_by_task):
        raise ValueError(f"the runs hold different tasks: {sorted(set(a_by_task) ^ set(b_by_task))}")
    if not a_by_task:
        raise ValueError("no task to compare")
    if n_boot < 1:
        raise ValueError(f"n_boot must be >= 1, got {n_boot}")
    if not 0.0 < level < 1.0:
        raise ValueError(f"level must be in (0, 1), got {level}")
    tasks = sorted(a_by_task)
    paired_tasks = set(tasks) if paired is True else set() if paired is False else set(paired)
    rng = np.random.default_rng(seed)
    observed = 0.0
    boot = np.zeros(n_boot)
    for task in tasks:
        a = _as_outcomes(a_by_task[task], f"run A, task {task}")
        b = _as_outcomes(b_by_task[task], f"run B, task {task}")
        if task in paired_tasks:
            if a.size != b.size:
                raise ValueError(f"task {task}: paired runs need as many episodes "
                                 f"({a.size} in A, {b.size} in B)")
            n = a.size
            only_b = int(np.sum(b & ~a))
            only_a = int(np.sum(a & ~b))
            observed += (only_b - only_a) / n
            kinds = np.array([only_b, only_a, n - only_b - only_a]) / n
            counts = rng.multinomial(n, kinds, size=n_boot)
            boot += (counts[:, 0] - counts[:, 1]) / n
        else:
            pa, pb = a.mean(), b.mean()
            observed += pb - pa
            boot += rng.binomial(b.size, pb, n_boot) / b.size - rng.binomial(a.size, pa, n_boot) / a.size
    k = len(tasks)
    tail = 100.0 * (1.0 - level) / 2.0
    low, high = np.percentile(boot / k, [tail, 100.0 - tail])
    return float(observed / k), float(low), float(high)


def paired_bootstrap_difference(a_by_task: Mapping[str, Sequence],
                                b_by_task: Mapping[str, Sequence], n_boot: int = 10000,
                                seed: int = 0) -> tuple[float, float, float]:
    """`bootstrap_difference` with every task paired: ``(B - A, low, high)`` at 95 %.

    Episode i of a task in `a_by_task` must be the same (task, seed, episode) as episode i in
    `b_by_task` (see `pair_records`)."""
    return bootstrap_difference(a_by_task, b_by_task, paired=True, n_boot=n_boot, seed=seed)


@dataclass(frozen=True)
class Pairing:
    """Episodes of two runs matched by (task, seed, episode), and what did not match.

    `pairs` keeps run A's record order.  A key repeated within a run (a damaged file) keeps its
    first record, as eval's loader does, and is counted in `duplicates_a` / `duplicates_b`."""

    pairs: dict[Key, tuple[dict, dict]]
    only_a: list[Key] = field(default_factory=list)
    only_b: list[Key] = field(default_factory=list)
    duplicates_a: int = 0
    duplicates_b: int = 0

    @property
    def unpaired(self) -> int:
        """Episodes that only one run holds."""
        return len(self.only_a) + len(self.only_b)

    @property
    def fully_paired(self) -> bool:
        """Both runs hold exactly the same episodes (and hold some)."""
        return bool(self.pairs) and not self.unpaired

    def tasks(self) -> list[str]:
        """Tasks with at least one pair, in run A's order."""
        return list(dict.fromkeys(k[0] for k in self.pairs))


def record_key(record: dict) -> Key:
    return record["task"], int(record["seed"]), int(record["episode"])


def _by_key(records: Iterable[dict]) -> tuple[dict[Key, dict], int]:
    out: dict[Key, dict] = {}
    duplicates = 0
    for r in records:
        key = record_key(r)
        if key in out:
            duplicates += 1
        else:
            out[key] = r
    return out, duplicates


def pair_records(records_a: Iterable[dict], records_b: Iterable[dict]) -> Pairing:
    """Pair two runs' episode records by (task, seed, episode) and report the rest.

    Two runs on the same (task, seed, episode) saw the same scene, so their outcomes are a
    paired sample; episodes only one run holds (other seeds, fewer episodes, other tasks) are
    listed in `only_a` / `only_b` so a report can say how much is unpaired."""
    a_by, dup_a = _by_key(records_a)
    b_by, dup_b = _by_key(records_b)
    pairs = {k: (r, b_by[k]) for k, r in a_by.items() if k in b_by}
    return Pairing(pairs=pairs, only_a=[k for k in a_by if k not in b_by],
                   only_b=[k for k in b_by if k not in a_by],
                   duplicates_a=dup_a, duplicates_b=dup_b)
