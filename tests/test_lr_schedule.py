"""The learning-rate schedule: halving by update count, in the pure function and in the trainer's SGD step."""

from __future__ import annotations

import _learner_helpers as H
import pytest

from romannet.common.config_learner import LearnerConfig
from romannet.common.errors import ConfigError
from romannet.learner.schedule import lr_at


def test_lr_is_constant_without_a_halving_period():
    assert lr_at(1e-4, 0, 0) == 1e-4
    assert lr_at(1e-4, 123_456, 0) == 1e-4


def test_lr_halves_once_per_period_of_updates_done():
    assert [lr_at(8.0, n, 10) for n in (0, 9, 10, 19, 20, 35)] == [8.0, 8.0, 4.0, 4.0, 2.0, 1.0]


def test_lr_at_rejects_a_negative_update_count():
    with pytest.raises(ValueError, match="updates_done"):
        lr_at(1e-4, -1, 10)


def test_config_rejects_a_negative_halving_period():
    with pytest.raises(ConfigError, match="lr_halve_every_updates"):
        LearnerConfig(lr_halve_every_updates=-5)


def test_trainer_steps_at_the_scheduled_rate_and_a_resumed_trainer_continues_it():
    t = H.trainer(lr=0.01, lr_halve_every_updates=2)
    tr = H.transition(primitive="push", reward=0.2)
    seen = []
    for _ in range(5):
        t.train_step([(tr, 1.0, 0)])
        seen.append(t.optimizer.param_groups[0]["lr"])
    assert seen == pytest.approx([0.01, 0.01, 0.005, 0.005, 0.0025])
    resumed = H.trainer(lr=0.01, lr_halve_every_updates=2)
    resumed.updates = 4  # what a checkpoint restores
    resumed.train_step([(tr, 1.0, 0)])
    assert resumed.optimizer.param_groups[0]["lr"] == pytest.approx(0.0025)
