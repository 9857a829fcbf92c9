"""exploration.q_smoothing_sigma_px: a decision chooses from Q maps blurred by a Gaussian (GR-ConvNet's
post-processing), so its argmax lands in the middle of a high-Q region; the recorded maps stay raw."""

from __future__ import annotations

import numpy as np
import pytest
from _learner_helpers import SMALL_MODEL

from romannet.common.config import ExplorationConfig
from romannet.common.configbase import ConfigError
from romannet.common.model import RoManNet
from romannet.common.policy import decide, smoothed_q

SHAPE = (32, 32)


def test_the_blurred_argmax_is_the_middle_of_a_plateau_not_a_spike_on_its_rim() -> None:
    q = np.zeros(SHAPE, np.float32)
    q[8:23, 8:23] = 1.0  # a 15 px plateau centred on (15, 15)
    q[8, 22] = 1.05  # a one-pixel spike on its corner
    assert np.unravel_index(int(np.argmax(q)), SHAPE) == (8, 22)
    blurred = smoothed_q(q, 3.0)
    assert blurred.shape == SHAPE and blurred.dtype == np.float32
    assert np.unravel_index(int(np.argmax(blurred)), SHAPE) == (15, 15)


def test_decide_chooses_from_the_blurred_maps_and_returns_the_raw_ones() -> None:
    model = RoManNet(SMALL_MODEL, seed=0)
    rng = np.random.default_rng(1)
    depth = (rng.random(SHAPE) * 0.05).astype(np.float32)
    color = (rng.random((*SHAPE, 3)) * 255).astype(np.uint8)
    plain, raw = decide(model, color, depth, False, 0.0, np.random.default_rng(0), ("pick",), ExplorationConfig(),
                        return_maps=True)
    cfg = ExplorationConfig(q_smoothing_sigma_px=4.0)
    action, maps = decide(model, color, depth, False, 0.0, np.random.default_rng(0), ("pick",), cfg, return_maps=True)
    assert np.array_equal(maps.q["pick"], raw.q["pick"])  # recorded and bootstrapped: the raw map
    expected = np.unravel_index(int(np.argmax(smoothed_q(raw.q["pick"], 4.0))), SHAPE)
    assert (action.row, action.col) == expected
    assert action.q_value == pytest.approx(float(raw.q["pick"][action.row, action.col]))  # its own raw Q
    assert (plain.row, plain.col) == np.unravel_index(int(np.argmax(raw.q["pick"])), SHAPE)


def test_q_smoothing_sigma_px_is_validated() -> None:
    with pytest.raises(ConfigError, match="q_smoothing_sigma_px"):
        ExplorationConfig(q_smoothing_sigma_px=-1.0)
