"""The learner's metrics: TensorBoard event files, a CSV, action images and learning-curve PNGs.

Everything lands in the run directory:
    <run_dir>/tensorboard/        event files (`tensorboard --logdir <run_dir>/tensorboard`)
    <run_dir>/metrics.csv         one row per update, fixed columns (COLUMNS), appended on resume
    <run_dir>/learning_curves.png loss per primitive, TD error, exploration rate, updates/s (redrawn
                                  every plot_every_s seconds and at close)
TensorBoard also gets, every image_every_updates updates, the executed action drawn on the colour
heightmap beside the executed net's Q map (tag `action/<primitive>`).

Scalars are passed by CSV column name (e.g. "loss_pick", "q_max_push", "updates_per_s"); the TensorBoard
tag is the name with its first `_` turned into `/` for per-primitive groups ("loss/pick").
"""

from __future__ import annotations

import csv
import logging
import math
import time
from collections.abc import Mapping
from pathlib import Path

import cv2
import numpy as np

from romannet.common.config import PRIMITIVES
from romannet.common.pictures import top_view

log = logging.getLogger(__name__)

_PER_PRIMITIVE = ("loss", "q_mean", "q_max")
COLUMNS: tuple[str, ...] = (
    "update", "wall_time_s", "loss",
    *(f"{stat}_{p}" for stat in _PER_PRIMITIVE for p in PRIMITIVES),
    "td_error_mean", "td_error_max", "explore_rate", "updates_per_s", "sample_latency_s", "step_time_s",
    "replay_size", "replay_inserts", "policy_lag", "weights_version", "batch_items", "skipped_items",
)
# Curves drawn in learning_curves.png: (panel title, columns).
_PANELS = (
    ("loss per primitive", tuple(f"loss_{p}" for p in PRIMITIVES)),
    ("TD error (mean |Y - Q|)", ("td_error_mean",)),
    ("LAE exploration rate", ("explore_rate",)),
    ("updates / s", ("updates_per_s",)),
)


def tag_of(column: str) -> str:
    """TensorBoard tag of a CSV column: per-primitive stats grouped as `<stat>/<primitive>`."""
    for stat in _PER_PRIMITIVE:
        for p in PRIMITIVES:
            if column == f"{stat}_{p}":
                return f"{stat}/{p}"
    group = {"td_error_mean": "td_error/mean", "td_error_max": "td_error/max", "explore_rate": "explore/rate",
             "replay_size": "replay/size", "replay_inserts": "replay/inserts", "policy_lag": "replay/policy_lag"}
    return group.get(column, f"learner/{column}")


def action_image(color_hm: np.ndarray, q_map: np.ndarray, row: int, col: int, angle_rad: float,
                 scale: int = 2) -> np.ndarray:
    """uint8 (h*scale, 2*w*scale, 3) RGB: the colour heightmap and the Q map (viridis-like colormap, scaled
    to its own min..max) side by side, the executed pixel circled and its angle drawn as a line on both.

    The angle is in the arrays' frame: 0 along +col, positive toward +row (the convention of common.action).
    Both are drawn seen from above, x right and y up (rows bottom-up), as every picture is (common.pictures).
    """
    h, w = q_map.shape
    q = np.nan_to_num(np.asarray(q_map, dtype=np.float32))
    span = float(q.max() - q.min())
    q8 = ((q - q.min()) / span * 255).astype(np.uint8) if span > 0 else np.zeros((h, w), np.uint8)
    q_rgb = cv2.cvtColor(cv2.applyColorMap(q8, cv2.COLORMAP_VIRIDIS), cv2.COLOR_BGR2RGB)
    panels = []
    row, angle_rad = h - 1 - row, -angle_rad  # to the top view's rows and turn
    for img in (top_view(np.asarray(color_hm[..., :3], dtype=np.uint8)), top_view(q_rgb)):
        big = cv2.resize(img, (w * scale, h * scale), interpolation=cv2.INTER_NEAREST)
        center = (int(col * scale + scale // 2), int(row * scale + scale // 2))
        radius = max(3, min(h, w) * scale // 20)
        tip = (int(center[0] + 2 * radius * math.cos(angle_rad)), int(center[1] + 2 * radius * math.sin(angle_rad)))
        cv2.circle(big, center, radius, (255, 0, 0), 1)
        cv2.line(big, center, tip, (255, 0, 0), 1)
        panels.append(big)
    return np.concatenate(panels, axis=1)


class LearnerMetrics:
    """Writes scalars to TensorBoard and the CSV, images to TensorBoard, curves to a PNG.

    image_every_updates: cadence of action images (0 = never); plot_every_s: seconds between curve redraws;
    first_update: transitions the first update needs, named in the picture while there is no update.
    Use as a context manager or call close().
    """

    def __init__(self, run_dir: str | Path, image_every_updates: int = 100, plot_every_s: float = 60.0,
                 first_update: int | None = None):
        from torch.utils.tensorboard import SummaryWriter  # heavy import: only where metrics are written

        self.run_dir = Path(run_dir)
        self.run_dir.mkdir(parents=True, exist_ok=True)
        self.image_every_updates = int(image_every_updates)
        self.plot_every_s = float(plot_every_s)
        self.csv_path = self.run_dir / "metrics.csv"
        self.plot_path = self.run_dir / "learning_curves.png"
        self.first_update = first_update
        self._history: dict[str, list[tuple[int, float]]] = {c: [] for _, cols in _PANELS for c in cols}
        self._load_history()
        new_file = not self.csv_path.exists() or self.csv_path.stat().st_size == 0
        # Line-buffered: the launcher's progress line reads the last row (one row per update, cheap).
        self._csv_file = self.csv_path.open("a", newline="", buffering=1)
        self._csv = csv.DictWriter(self._csv_file, fieldnames=COLUMNS, extrasaction="ignore")
        if new_file:
            self._csv.writeheader()
        self._writer = SummaryWriter(log_dir=str(self.run_dir / "tensorboard"))
        self._next_plot_s = time.monotonic() + self.plot_every_s
        self._started = time.time()

    def _load_history(self) -> None:
        """On resume, the curves continue from the rows already in the CSV."""
        if not self.csv_path.exists():
            return
        with self.csv_path.open(newline="") as f:
            for row in csv.DictReader(f):
                self._remember(row)

    def _remember(self, row: Mapping[str, object]) -> None:
        try:
            update = int(float(row["update"]))  # type: ignore[arg-type]
        except (KeyError, TypeError, ValueError):
            return
        for column, points in self._history.items():
            value = row.get(column)
            if value not in (None, ""):
                try:
                    points.append((update, float(value)))  # type: ignore[arg-type]
                except (TypeError, ValueError):
                    continue

    def log_scalars(self, update: int, values: Mapping[str, float | int | None]) -> None:
        """One CSV row and one TensorBoard point per finite value, at step `update`."""
        row: dict[str, object] = {"update": update, "wall_time_s": round(time.time() - self._started, 3)}
        for column, value in values.items():
            if value is None or column not in COLUMNS:
                continue
            value = float(value)
            if not math.isfinite(value):
                continue
            row[column] = value
            self._writer.add_scalar(tag_of(column), value, update)
        self._csv.writerow(row)
        self._remember(row)
        if time.monotonic() >= self._next_plot_s:
            self.plot()

    def wants_image(self, update: int) -> bool:
        """Whether an action image is due at this update."""
        return self.image_every_updates > 0 and update % self.image_every_updates == 0

    def log_action_image(self, update: int, primitive: str, color_hm: np.ndarray, q_map: np.ndarray,
                         row: int, col: int, angle_rad: float) -> None:
        """The executed action on the heightmap beside the Q map, as TensorBoard image `action/<primitive>`."""
        image = action_image(color_hm, q_map, row, col, angle_rad)
        self._writer.add_image(f"action/{primitive}", image, update, dataformats="HWC")

    def plot(self) -> None:
        """Redraw learning_curves.png (atomically: written beside, then renamed)."""
        import matplotlib.pyplot as plt

        self._next_plot_s = time.monotonic() + self.plot_every_s
        fig = self.figure()
        try:
            tmp = self.plot_path.with_suffix(".tmp.png")
            fig.savefig(tmp, dpi=80)
            tmp.replace(self.plot_path)
        finally:
            plt.close(fig)

    def figure(self):  # -> matplotlib.figure.Figure (matplotlib is imported only where a picture is drawn)
        """The learning curves as a figure; without any update yet, a line in it says why it is empty."""
        import matplotlib

        matplotlib.use("Agg")  # no display on a learner box; must precede pyplot's import
        import matplotlib.pyplot as plt

        fig, axes = plt.subplots(len(_PANELS), 1, figsize=(8, 2.4 * len(_PANELS)), sharex=True)
        for ax, (title, columns) in zip(axes, _PANELS, strict=True):
            for column in columns:
                points = self._history[column]
                if points:
                    xs, ys = zip(*points, strict=True)
                    ax.plot(xs, ys, label=column, linewidth=0.8)
            ax.set_title(title, fontsize=9)
            if len(columns) > 1 and any(self._history[c] for c in columns):
                ax.legend(fontsize=7)
            ax.grid(alpha=0.3)
        axes[-1].set_xlabel("update")
        fig.tight_layout()
        if not any(self._history.values()):
            fig.text(0.5, 0.5, self.no_update_note(), ha="center", va="center", fontsize=11, wrap=True,
                     bbox={"boxstyle": "round", "facecolor": "lightyellow", "edgecolor": "0.5"})
        return fig

    def no_update_note(self) -> str:
        """What the empty picture says: no update, and what the first one waits for."""
        need = "" if self.first_update is None else f"\nthe first needs {self.first_update} transitions in replay"
        return f"no learner update yet{need}\n(replay.min_size_to_sample, learner.min_replay_size)"

    def flush(self) -> None:
        """Push buffered rows and events to disk (at checkpoints, so files and checkpoint agree)."""
        self._csv_file.flush()
        self._writer.flush()

    def close(self) -> None:
        """Final plot, flush and close. Idempotent."""
        if self._csv_file.closed:
            return
        try:
            self.plot()
        except Exception as exc:  # a plotting failure must not lose the checkpoint path's shutdown
            log.warning("could not draw %s: %s", self.plot_path, exc)
        self._writer.close()
        self._csv_file.close()

    def __enter__(self) -> LearnerMetrics:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
