"""A run's own training curves, kept up to date: RUN_DIR/training_curves.png (romannet.evaluate.run_figure)
and RUN_DIR/tensorboard/episodes/ (romannet.evaluate.run_board), both from the run's recorded episodes
(romannet.evaluate.run_curves, the source `romannet plot` reads too).

`romannet up` keeps a LiveRunReport: a thread redraws both every `every_s` seconds while the fleet runs,
and once more after the actors stopped, so the files end with every action. A failure to draw is logged
(once per kind) and never stops the run.
"""

from __future__ import annotations

import logging
import threading
from pathlib import Path

from romannet.common.config import load_config
from romannet.common.configbase import to_dict

from .run_board import CurvesBoard, flat_hparams
from .run_curves import EpisodeFiles, RunCurves, compute
from .run_figure import draw

log = logging.getLogger(__name__)

PNG_NAME = "training_curves.png"
BOARD_DIR = ("tensorboard", "episodes")


class RunReport:
    """Reads a run's episodes (incrementally), draws its PNG and, with board=True, writes its TensorBoard
    curves. Raises ConfigError (one line) for a run directory without a loadable config.toml."""

    def __init__(self, run_dir: Path, window: int = 200, episode_window: int = 20, board: bool = True):
        config_path = run_dir / "config.toml"
        cfg = load_config(config_path)
        self.run_dir, self.window, self.episode_window = run_dir, window, episode_window
        self.title = f"{run_dir.name} ({cfg.task.kind}" + (
            f", goal height {cfg.task.goal_stack_height})" if cfg.task.kind == "stacking" else ")")
        self._files = EpisodeFiles(run_dir, cfg.task.kind, cfg.task.goal_stack_height)
        self._board = CurvesBoard(run_dir.joinpath(*BOARD_DIR), config_path.read_text(encoding="utf-8"),
                                  flat_hparams(to_dict(cfg)), stride=max(1, window // 20)) if board else None

    def curves(self) -> RunCurves:
        return compute(self._files.read(), self.window, self.episode_window)

    def refresh(self, png: Path | None = None) -> RunCurves:
        """Read what is new, redraw the PNG (RUN_DIR/training_curves.png unless given) and add the new
        TensorBoard points; returns the curves."""
        curves = self.curves()
        draw(curves, png or self.run_dir / PNG_NAME, self.title)
        if self._board is not None:
            self._board.write(curves)
        return curves

    def close(self) -> None:
        if self._board is not None:
            self._board.close()


class LiveRunReport:
    """RunReport.refresh every `every_s` seconds on a thread; `close` stops it and refreshes a last time."""

    def __init__(self, run_dir: Path, window: int, every_s: float = 60.0):
        self._report = RunReport(run_dir, window)
        self._every_s = every_s
        self._stop = threading.Event()
        self._failed: set[str] = set()
        self._thread = threading.Thread(target=self._loop, name="run-report", daemon=True)
        self._thread.start()

    def _refresh(self) -> None:
        try:
            self._report.refresh()
        except Exception as exc:  # curves are for people: a broken drawing must not stop the training
            kind = type(exc).__name__
            if kind not in self._failed:
                self._failed.add(kind)
                log.warning("could not draw the run's curves (%s): %s", kind, exc)

    def _loop(self) -> None:
        while not self._stop.wait(self._every_s):
            self._refresh()

    def close(self) -> None:
        """Stop the thread, draw everything once more (call it after the actors stopped), close the events."""
        self._stop.set()
        self._thread.join()
        self._refresh()
        self._report.close()
