"""The learner's learning_curves.png: a run that ends before the first update says so in the picture
instead of leaving four empty panels."""

from __future__ import annotations

from pathlib import Path

import matplotlib.pyplot as plt

from romannet.learner.metrics import LearnerMetrics


def _texts(metrics: LearnerMetrics) -> list[str]:
    fig = metrics.figure()
    try:
        return [t.get_text() for t in fig.texts]
    finally:
        plt.close(fig)


def test_the_picture_says_why_it_is_empty_until_the_first_update(tmp_path: Path) -> None:
    with LearnerMetrics(tmp_path, image_every_updates=0, first_update=64) as metrics:
        [note] = _texts(metrics)
        assert note.startswith("no learner update yet") and "needs 64 transitions in replay" in note, note
        metrics.log_scalars(1, {"loss_pick": 0.5, "explore_rate": 0.3})
        assert _texts(metrics) == []
    assert (tmp_path / "learning_curves.png").stat().st_size > 0


def test_a_resumed_run_draws_its_earlier_updates_without_the_note(tmp_path: Path) -> None:
    with LearnerMetrics(tmp_path, image_every_updates=0) as metrics:
        metrics.log_scalars(1, {"td_error_mean": 0.2})
    with LearnerMetrics(tmp_path, image_every_updates=0, first_update=64) as metrics:
        assert _texts(metrics) == []
