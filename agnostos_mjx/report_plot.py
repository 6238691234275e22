"""Bar plot of an evaluation summary (PNG), optionally beside published numbers."""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

log = logging.getLogger("agnostos_mjx.eval")


def plot_summary(summary: dict, path: Path, title: str = "",
                 compare: dict[str, float] | None = None, compare_label: str = "") -> bool:
    """Write a horizontal bar chart of per-task and group success (mean +- std
    over seeds).  Returns False (with a log line) when matplotlib is missing."""
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        log.info("matplotlib not installed; skipping %s (pip install agnostos-mjx[plot])", path)
        return False
    rows = [(n, t["success_mean"], t["success_std"]) for n, t in summary["tasks"].items()]
    rows += [(f"[{g}]", v["success_mean"], v["success_std"]) for g, v in summary["groups"].items()]
    names = [r[0] for r in rows]
    y = np.arange(len(rows))
    fig, ax = plt.subplots(figsize=(8, 0.28 * len(rows) + 1.2))
    height = 0.4 if compare else 0.8
    ax.barh(y, [r[1] for r in rows], height, xerr=[r[2] for r in rows], color="#3b7dd8",
            label="this run", capsize=2)
    if compare:
        ref = [compare.get(n.strip("[]"), np.nan) for n in names]
        ax.barh(y + height, ref, height, color="#bbbbbb", label=compare_label)
        ax.legend(loc="lower right", fontsize=8)
    ax.set_yticks(y + (height / 2 if compare else 0), names, fontsize=7)
    ax.invert_yaxis()
    ax.set_xlim(0, 100)
    ax.set_xlabel("success % (mean and std over seeds)")
    ax.set_title(title, fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return True
