"""The PNG of one run's training curves (romannet.evaluate.run_curves), over training actions:

    action success rate and efficiency   (%, over the last `window` actions; `romannet plot`'s curve)
    episode completion                   (%, of the last `episode_window` finished episodes)
    episode return                       (each episode a dot, their rolling mean a line)
    episode length                       (actions; dots and rolling mean)
    actions per second                   (the whole fleet's, over the last `window` actions)

`romannet plot RUN_DIR` draws it for one run; `romannet up` redraws it as RUN_DIR/training_curves.png.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from .run_curves import RunCurves, rolling_mean

PANELS = ("Action success and efficiency", "Episode completion", "Episode return", "Episode length",
          "Actions per second")


def _empty(ax, what: str) -> None:  # noqa: ANN001 (a matplotlib Axes)
    ax.text(0.5, 0.5, f"no {what} yet", transform=ax.transAxes, ha="center", va="center", color="0.5")


def _episodes(ax, curves: RunCurves, values: np.ndarray, color: str, label: str) -> None:  # noqa: ANN001
    if not len(values):
        _empty(ax, "finished episode")
        return
    ax.scatter(curves.episode_x, values, s=9, color=color, alpha=0.5, linewidths=0, label="each episode")
    ax.plot(curves.episode_x, rolling_mean(values, curves.episode_window), color=color,
            label=f"{label}, mean of the last {curves.episode_window}")
    ax.legend(fontsize=7, loc="upper left")


def draw(curves: RunCurves, out: Path, title: str) -> Path:
    """Write the five panels to `out` (PNG, atomically: written beside, then renamed); returns out."""
    import matplotlib

    matplotlib.use("Agg")  # no display needed; must precede pyplot's import
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(len(PANELS), 1, figsize=(8, 11), sharex=True)
    try:
        ax = axes[0]
        if len(curves.action_x):
            ax.plot(curves.action_x, 100 * curves.success_rate, color="C0", label="action success")
            ax.plot(curves.action_x, 100 * curves.efficiency, color="C0", linestyle=":", label="action efficiency")
            ax.legend(fontsize=7, loc="upper left")
        else:
            _empty(ax, "action")
        ax.set_ylabel(f"% of the last\n{curves.window} actions")
        ax.set_ylim(0, 100)
        ax = axes[1]
        if curves.episodes:
            ax.plot(curves.episode_x, 100 * curves.completion_rate, color="C2")
        else:
            _empty(ax, "finished episode")
        ax.set_ylabel(f"% of the last\n{curves.episode_window} episodes")
        ax.set_ylim(0, 100)
        _episodes(axes[2], curves, curves.episode_return, "C1", "return")
        axes[2].set_ylabel("sum of rewards")
        _episodes(axes[3], curves, curves.episode_length, "C4", "length")
        axes[3].set_ylabel("actions")
        ax = axes[4]
        if np.isfinite(curves.actions_per_s).any():
            ax.plot(curves.action_x, curves.actions_per_s, color="C5")
            ax.set_ylim(bottom=0)
        else:
            _empty(ax, "action rate")
        ax.set_ylabel(f"actions / s (last\n{curves.window} actions)")
        ax.set_xlabel("training actions (all actors)")
        for ax, name in zip(axes, PANELS, strict=True):
            ax.set_title(name, fontsize=9, loc="left")
            ax.grid(alpha=0.3)
        fig.suptitle(f"{title}: {curves.actions} actions, {curves.episodes} episodes ({curves.completed} completed)",
                     fontsize=10)
        fig.tight_layout()
        out.parent.mkdir(parents=True, exist_ok=True)
        tmp = out.with_suffix(".tmp.png")
        fig.savefig(tmp, dpi=90)
        tmp.replace(out)
    finally:
        plt.close(fig)
    return out
