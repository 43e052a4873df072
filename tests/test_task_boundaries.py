"""The task's thresholds at their exact boundaries, objects that start above the origin and
non-default task specs (mutation testing found these unchecked; see scripts/mutation.py)."""

import math

import numpy as np
import pytest

from dexdrake.errors import DexdrakeError
from dexdrake.task import TARGET_THRESHOLDS, SuccessTracker, TaskSpec, reward_terms, target_position

TABLE = np.array([0.3, -0.1, 0.05])  # an object resting on a table, not at the origin


def _offset_with_square(d2: float) -> np.ndarray:
    """A horizontal offset whose squared norm, summed in float as the task does, is exactly d2."""
    for i in range(1, 2000):
        y = i * 1e-4
        x = math.sqrt(d2 - y * y)
        for _ in range(4):
            offset = np.array([x, y, 0.0])
            total = float(np.sum(offset**2))
            if total == d2:
                return offset
            x = math.nextafter(x, 1.0 if total < d2 else 0.0)
    raise AssertionError(f"no offset with squared norm {d2}")


def test_object_resting_above_the_origin_is_not_lifted():
    terms = reward_terms(np.zeros(5), TABLE.copy(), TABLE.copy())
    assert terms.r_g == 0 and terms.r_t == 0


def test_lift_must_exceed_the_threshold():
    start = np.zeros(3)
    at_threshold = reward_terms(np.zeros(5), np.array([0.0, 0.0, 0.02]), start)
    assert at_threshold.r_g == 0 and at_threshold.r_t == 0
    above = reward_terms(np.zeros(5), np.array([0.0, 0.0, 0.0201]), start)
    assert above.r_g == 1


@pytest.mark.parametrize("reward", sorted(TARGET_THRESHOLDS))
def test_target_bonus_thresholds_are_strict(reward):
    start, spec = np.zeros(3), TaskSpec(reward=reward)
    near, far = TARGET_THRESHOLDS[reward]
    for d2, below, at in [(near, 20.0, 10.0), (far, 10.0, 0.0)]:
        offset = _offset_with_square(d2)
        assert reward_terms(np.zeros(5), offset + [0, 0, 0.15], start, spec).r_t == at
        inside = offset * (1 - 1e-9) + [0, 0, 0.15]
        assert reward_terms(np.zeros(5), inside, start, spec).r_t == below


def test_aligned_reward_pays_the_target_bonus_only_inside_the_success_radius():
    start = np.zeros(3)
    spec = TaskSpec(reward="aligned")
    carried_off = target_position(start) + [0.12, 0.0, 0.0]  # lifted, 0.12 m beside the target
    assert reward_terms(np.zeros(5), carried_off, start).r_t == 20.0  # the paper's formula pays in full
    assert reward_terms(np.zeros(5), carried_off, start, spec).r_t == 0.0
    assert reward_terms(np.zeros(5), carried_off - [0.04, 0, 0], start, spec).r_t == 10.0
    assert reward_terms(np.zeros(5), carried_off - [0.09, 0, 0], start, spec).r_t == 20.0
    assert TARGET_THRESHOLDS["aligned"][1] == pytest.approx(TaskSpec().success_radius**2)


def test_unknown_reward_is_refused():
    with pytest.raises(DexdrakeError, match="unknown reward 'dense'"):
        TaskSpec(reward="dense")


def test_target_height_of_the_spec_is_used():
    spec = TaskSpec(target_height=0.4)
    np.testing.assert_allclose(target_position(TABLE, spec), TABLE + [0, 0, 0.4])
    # 0.4 m up is on this spec's target; 0.15 m up (the default target) is 0.0625 away in d^2.
    assert reward_terms(np.zeros(5), TABLE + [0, 0, 0.4], TABLE, spec).r_t == 20.0
    assert reward_terms(np.zeros(5), TABLE + [0, 0, 0.15], TABLE, spec).r_t == 10.0


def test_success_counts_against_the_specs_target():
    spec = TaskSpec(target_height=0.4, success_steps=2)
    on_target = SuccessTracker(TABLE.copy(), spec)
    assert not on_target.update(TABLE + [0, 0, 0.4]) and on_target.update(TABLE + [0, 0, 0.4])
    default_height = SuccessTracker(TABLE.copy(), spec)
    for _ in range(3):
        default_height.update(TABLE + [0, 0, 0.15])
    assert default_height.best_streak == 0 and not default_height.success


def test_success_radius_is_strict():
    spec = TaskSpec(success_steps=1)
    target = target_position(np.zeros(3), spec)
    tracker = SuccessTracker(np.zeros(3), spec)
    assert not tracker.update(target + [spec.success_radius, 0, 0])
    assert tracker.update(target + [math.nextafter(spec.success_radius, 0.0), 0, 0])


def test_max_lift_is_measured_from_the_start_height():
    tracker = SuccessTracker(TABLE.copy())
    tracker.update(TABLE + [0, 0, 0.03])
    tracker.update(TABLE.copy())
    assert tracker.max_lift == pytest.approx(0.03)
