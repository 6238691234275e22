"""Bar plot of an evaluation summary (PNG), optionally beside published numbers."""

from __future__ import annotations

import logging
from pathlib import Path
from types import ModuleType

import numpy as np

log = logging.getLogger("agnostos_mjx.eval")


def pyplot() -> ModuleType | None:
    """matplotlib's pyplot on the Agg backend, None without matplotlib.  Its import takes
    ~1 s: the launcher of a multi-process run calls this while its processes run, so that
    the merge at the end does not wait for it."""
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        return None
    return plt


def plot_summary(summary: dict, path: Path, title: str = "",
                 compare: dict[str, float] | None = None, compare_label: str = "") -> bool:
    """Write a horizontal bar chart of per-task and group success: the bar is the mean over
    seeds, the whisker the Wilson 95 % interval of the pooled episodes (wider, and honest
    about 75 episodes, than the std over 3 seeds).  Returns False (with a log line) when
    matplotlib is missing."""
    plt = pyplot()
    if plt is None:
        log.info("matplotlib not installed; skipping %s (pip install agnostos-mjx[plot])", path)
        return False
    items = [(n, t) for n, t in summary["tasks"].items()]
    items += [(f"[{g}]", v) for g, v in summary["groups"].items()]
    rows = [(n, v["success_mean"], v["wilson95"]) for n, v in items]
    names = [r[0] for r in rows]
    y = np.arange(len(rows))
    fig, ax = plt.subplots(figsize=(8, 0.28 * len(rows) + 1.2))
    height = 0.4 if compare else 0.8
    mean = np.array([r[1] for r in rows])
    low, high = np.array([r[2][0] for r in rows]), np.array([r[2][1] for r in rows])
    # A seed-mean can sit just outside the pooled interval; whiskers never go negative.
    err = np.maximum(np.stack([mean - low, high - mean]), 0.0)
    ax.barh(y, mean, height, xerr=err, color="#3b7dd8", label="this run", capsize=2)
    if compare:
        ref = [compare.get(n.strip("[]"), np.nan) for n in names]
        ax.barh(y + height, ref, height, color="#bbbbbb", label=compare_label)
        ax.legend(loc="lower right", fontsize=8)
    ax.set_yticks(y + (height / 2 if compare else 0), names, fontsize=7)
    ax.invert_yaxis()
    ax.set_xlim(0, 100)
    ax.set_xlabel("success % (mean over seeds; whiskers: Wilson 95 % interval)")
    ax.set_title(title, fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return True
