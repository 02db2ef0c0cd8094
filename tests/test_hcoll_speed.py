"""bench/hcoll_speed.py: body speed, trailing means and the correlation on hand-made sequences."""

from __future__ import annotations

import math

import numpy as np

from tests.script_loader import load_script

hcoll_speed = load_script("bench/hcoll_speed.py")


def test_body_speed_of_a_translating_body():
    # 4 vertices moving 2 cm per frame along y from frame 3 on
    t = np.arange(8, dtype=float)
    y = np.clip(t - 2, 0, None) * 0.02
    v = np.zeros((8, 4, 3))
    v[:, :, 1] = y[:, None]
    np.testing.assert_allclose(hcoll_speed.body_speed(v), [0, 0, 0, 0.02, 0.02, 0.02, 0.02, 0.02])


def test_trailing_mean_uses_fewer_frames_at_the_start():
    np.testing.assert_allclose(hcoll_speed.trailing_mean(np.array([2.0, 4.0, 6.0, 8.0]), 2), [2, 3, 5, 7])


def test_correlation_is_one_for_penetration_that_follows_the_speed_and_nan_for_constant():
    speed = np.abs(np.sin(np.linspace(0, 6, 60)))
    h = 3.0 * hcoll_speed.trailing_mean(speed, 5) + 0.1
    assert math.isclose(hcoll_speed.speed_correlation(h, speed, 5), 1.0, abs_tol=1e-9)
    assert math.isclose(hcoll_speed.speed_correlation(-h, speed, 5), -1.0, abs_tol=1e-9)
    assert math.isnan(hcoll_speed.speed_correlation(np.ones(60), speed, 5))
