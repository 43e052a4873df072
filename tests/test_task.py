import numpy as np
import pytest

from dexdrake.task import SuccessTracker, TaskSpec, reward_terms, target_position


def test_reward_distance_term_matches_formula():
    d = np.array([0.01, 0.02, 0.0, 0.03, 0.04])
    terms = reward_terms(d, np.zeros(3), np.zeros(3))
    assert terms.r_d == pytest.approx(0.1 * (1 / (10 * 0.10 + 0.25) - 1))
    assert terms.r_g == 0 and terms.r_t == 0


def test_resting_object_earns_no_target_bonus():
    # Literal paper formula would pay 20 here (0.15^2 < 0.05); we gate r_t on lifting.
    assert reward_terms(np.zeros(5), np.zeros(3), np.zeros(3)).r_t == 0


@pytest.mark.parametrize("lift,r_t", [(0.15, 20.0), (0.03, 20.0), (0.021, 20.0)])
def test_lifted_object_earns_target_bonus(lift, r_t):
    terms = reward_terms(np.zeros(5), np.array([0, 0, lift]), np.zeros(3))
    assert terms.r_g == 1 and terms.r_t == r_t


def test_target_bonus_tiers_by_squared_distance():
    start = np.zeros(3)
    far = reward_terms(np.zeros(5), np.array([0.27, 0, 0.15]), start)  # d^2 = 0.0729
    assert far.r_t == 10
    very_far = reward_terms(np.zeros(5), np.array([0.4, 0, 0.15]), start)  # d^2 = 0.16
    assert very_far.r_t == 0


def test_success_needs_consecutive_steps_near_target():
    spec = TaskSpec(success_steps=3)
    tracker = SuccessTracker(np.zeros(3), spec)
    near, away = target_position(np.zeros(3), spec), np.zeros(3)
    for p in (near, near, away, near, near):
        tracker.update(p)
    assert not tracker.success and tracker.best_streak == 2
    tracker.update(near)
    assert tracker.success
    assert tracker.max_lift == pytest.approx(0.15)
