"""agnostos_mjx.infra.stats: Wilson intervals, exact McNemar, the stratified bootstrap, pairing.

scipy (a dev dependency only) cross-checks the numbers; the package itself does not need it."""

from __future__ import annotations

import numpy as np
import pytest

from agnostos_mjx.infra import stats

scipy_stats = pytest.importorskip("scipy.stats")
Z95 = float(scipy_stats.norm.ppf(0.975))  # scipy's z; the default 1.96 differs in the 4th digit


@pytest.mark.parametrize("k,n", [(0, 75), (75, 75), (10, 75), (1, 3), (37, 75), (74, 75), (1, 1)])
def test_wilson_matches_scipy(k, n):
    ci = scipy_stats.binomtest(k, n).proportion_ci(confidence_level=0.95, method="wilson")
    assert stats.wilson_interval(k, n, z=Z95) == pytest.approx((ci.low, ci.high), abs=1e-12)
    assert stats.wilson_interval(k, n) == pytest.approx((ci.low, ci.high), abs=1e-4)


def test_wilson_ends_vectorised_and_empty():
    assert stats.wilson_interval(0, 75)[0] == 0.0 and stats.wilson_interval(75, 75)[1] == 1.0
    assert stats.wilson_interval(0, 75)[1] == pytest.approx(0.0487, abs=1e-4)  # not zero width
    assert stats.wilson_interval(0, 0) == (0.0, 1.0)  # no episode: any rate
    low, high = stats.wilson_interval(np.array([0, 10, 75, 0]), np.array([75, 75, 75, 0]))
    assert low.shape == (4,) and np.all(low <= high) and np.all((low >= 0) & (high <= 1))
    assert (low[1], high[1]) == stats.wilson_interval(10, 75)
    assert (low[3], high[3]) == (0.0, 1.0)
    for bad in ((5, 4), (-1, 4), (1, -1)):
        with pytest.raises(ValueError):
            stats.wilson_interval(*bad)


def test_mcnemar_matches_scipy_binomtest():
    assert stats.mcnemar_exact(0, 0) == 1.0
    for b in range(0, 26):
        for c in range(0, 26):
            if b + c == 0:
                continue
            expected = scipy_stats.binomtest(b, b + c, 0.5).pvalue
            assert stats.mcnemar_exact(b, c) == pytest.approx(expected, rel=1e-12, abs=1e-300)
            assert stats.mcnemar_exact(b, c) == stats.mcnemar_exact(c, b)
    assert stats.mcnemar_exact(0, 5) == pytest.approx(2 / 32)
    assert stats.mcnemar_exact(7, 7) == 1.0
    with pytest.raises(ValueError):
        stats.mcnemar_exact(-1, 2)


@pytest.mark.parametrize("b,c", [(1000, 1100), (1900, 2000), (3000, 3300), (5000, 5000),
                                 (2500, 2600), (10, 4000)])
def test_mcnemar_large_counts_exact_and_log_space(b, c):
    expected = scipy_stats.binomtest(b, b + c, 0.5).pvalue
    assert stats.mcnemar_exact(b, c) == pytest.approx(expected, rel=1e-9, abs=1e-300)


def _runs(rng, tasks=("t1", "t2", "t3"), n=75, pa=0.3, pb=0.45):
    a = {t: rng.random(n) < pa for t in tasks}
    # B agrees with A on most episodes (same scenes), so pairing removes most of the noise.
    b = {t: np.where(rng.random(n) < 0.8, a[t], rng.random(n) < pb) for t in tasks}
    return a, b


def test_bootstrap_identical_runs_zero_width_and_deterministic():
    a, b = _runs(np.random.default_rng(1))
    assert stats.paired_bootstrap_difference(a, a) == (0.0, 0.0, 0.0)
    first = stats.paired_bootstrap_difference(a, b, n_boot=2000, seed=3)
    assert stats.paired_bootstrap_difference(a, b, n_boot=2000, seed=3) == first
    # The task order of the mappings does not matter.
    assert stats.paired_bootstrap_difference(dict(reversed(a.items())), dict(reversed(b.items())),
                                             n_boot=2000, seed=3) == first
    # Another seed, other resamples (the interval ends lie on a grid of 1/225: some may tie).
    assert any(stats.paired_bootstrap_difference(a, b, n_boot=2000, seed=s) != first
               for s in range(4, 10))
    diff, low, high = first
    expected = np.mean([b[t].mean() - a[t].mean() for t in a])
    assert diff == pytest.approx(expected) and low < diff < high


def test_bootstrap_matches_naive_index_resampling():
    """Counts drawn from a multinomial are the same distribution as resampled episode indices."""
    rng = np.random.default_rng(7)
    a, b = _runs(rng)
    n_boot = 20000
    naive = np.zeros(n_boot)
    for t in a:
        idx = rng.integers(0, a[t].size, size=(n_boot, a[t].size))
        naive += (b[t][idx].mean(1) - a[t][idx].mean(1)) / len(a)
    _, low, high = stats.paired_bootstrap_difference(a, b, n_boot=n_boot, seed=0)
    assert (low, high) == pytest.approx(tuple(np.percentile(naive, [2.5, 97.5])), abs=0.01)
    # Unpaired: each run on its own.
    naive = np.zeros(n_boot)
    for t in a:
        ia = rng.integers(0, a[t].size, size=(n_boot, a[t].size))
        ib = rng.integers(0, b[t].size, size=(n_boot, b[t].size))
        naive += (b[t][ib].mean(1) - a[t][ia].mean(1)) / len(a)
    _, ulow, uhigh = stats.bootstrap_difference(a, b, paired=False, n_boot=n_boot, seed=0)
    assert (ulow, uhigh) == pytest.approx(tuple(np.percentile(naive, [2.5, 97.5])), abs=0.01)
    assert uhigh - ulow > 1.5 * (high - low)  # pairing pays on shared scenes


def test_bootstrap_mixed_pairing_and_errors():
    a, b = _runs(np.random.default_rng(2))
    b["t3"] = b["t3"][:50]  # t3: other episodes, unpaired
    diff, low, high = stats.bootstrap_difference(a, b, paired={"t1", "t2"}, n_boot=2000)
    assert low <= diff <= high
    with pytest.raises(ValueError, match="as many episodes"):
        stats.paired_bootstrap_difference(a, b)
    with pytest.raises(ValueError, match="different tasks"):
        stats.paired_bootstrap_difference(a, {"t1": b["t1"]})
    with pytest.raises(ValueError, match="non-empty"):
        stats.paired_bootstrap_difference({"t": []}, {"t": []})


def test_pair_records_reports_unpaired_and_duplicates():
    def rec(task, seed, ep):
        return {"task": task, "seed": seed, "episode": ep, "success": True}

    a = [rec("x", 0, 0), rec("x", 0, 1), rec("y", 0, 0), rec("x", 0, 0)]
    b = [rec("x", 0, 1), rec("x", 0, 0), rec("x", 1, 0), rec("z", 0, 0)]
    p = stats.pair_records(a, b)
    assert list(p.pairs) == [("x", 0, 0), ("x", 0, 1)]  # run A's order
    assert p.pairs[("x", 0, 0)] == (a[0], b[1])
    assert (p.only_a, p.only_b) == ([("y", 0, 0)], [("x", 1, 0), ("z", 0, 0)])
    assert (p.unpaired, p.duplicates_a, p.duplicates_b, p.fully_paired) == (3, 1, 0, False)
    assert p.tasks() == ["x"]
    assert stats.pair_records(a[:2], b[:2]).fully_paired


def test_summary_reports_wilson_intervals_per_task_and_group(tmp_path):
    """results.csv/.md carry the Wilson 95 % interval of each task's and group's pooled
    episodes (a group pools its tasks' episodes)."""
    from agnostos_mjx.evaluation.summary import aggregate, csv_rows, format_markdown
    from agnostos_mjx.infra.stats import wilson_interval

    records = [{"task": t, "split": "unseen_level1", "seed": s, "episode": e,
                "success": e < k, "outcome": "success" if e < k else "max_steps",
                "key_actions": 1, "sim_steps": 10}
               for t, k in (("a", 5), ("b", 25)) for s in (0, 1, 2) for e in range(25)]
    summary = aggregate(records)
    low, high = wilson_interval(15, 75)
    assert summary["tasks"]["a"]["wilson95"] == [round(100 * low, 2), round(100 * high, 2)]
    assert summary["tasks"]["b"]["wilson95"][1] == 100.0
    low, high = wilson_interval(90, 150)
    assert summary["groups"]["All"]["wilson95"] == [round(100 * low, 2), round(100 * high, 2)]
    rows = {r["name"]: r for r in csv_rows(summary)}
    assert rows["a"]["success_pct_ci_low"] == summary["tasks"]["a"]["wilson95"][0]
    assert rows["All"]["success_pct_ci_high"] == summary["groups"]["All"]["wilson95"][1]
    md = format_markdown(summary)
    assert "| a | unseen_level1 | 20.0 (0.0) | [{:.1f}, {:.1f}] |".format(
        *summary["tasks"]["a"]["wilson95"]) in md
