"""Allegro Hand v4 bus units: the one source of truth for the CAN driver's conversions.

Every number here is transcribed from specs/allegro_v4.md ("Bus" and "Session" sections).
Arrays are in CAN bus order: finger 0 = index (joint_0.0..joint_3.0), 1 = middle (4-7),
2 = ring (8-11), 3 = thumb (12-15); within a finger j0 is spread, j1-j3 flexion.
Multi-byte payload fields are little-endian int16.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import ArrayLike

from dexdrake.errors import DexdrakeError

NUM_JOINTS = 16
JOINTS_PER_FINGER = 4
BUS_JOINT_NAMES: tuple[str, ...] = tuple(f"joint_{k}.0" for k in range(NUM_JOINTS))

#: rad per encoder count: rad = counts * 333.3 / 65536 * pi / 180 (about 8.876e-5).
#: The manual's printed formula is wrong; every working driver uses this one.
RAD_PER_COUNT = 333.3 / 65536 * math.pi / 180

#: PWM duty for a normalised torque of 1: 1200 on v4 at 12 V (v3 at 8 V: 800; 24 V: 500).
PWM_SCALE_12V = 1200.0

#: Per-joint PWM limits of the vendor driver: fingers j0..j3 375, 675, 450, 285;
#: thumb 525, 405, 270, 270.
PWM_LIMITS = np.array(3 * [375, 675, 450, 285] + [525, 405, 270, 270], dtype=float)

#: Vendor PD gains in PWM counts per rad (Kp) and per rad/s (Kd).
KP_VENDOR = np.array(3 * [500, 800, 900, 500] + [1000, 700, 600, 600], dtype=float)
KD_VENDOR = np.array(3 * [25, 50, 55, 40] + [50, 50, 50, 40], dtype=float)

_INT16 = np.iinfo(np.int16)


def counts_to_rad(counts: ArrayLike) -> np.ndarray:
    """Joint positions in rad from encoder counts (int16 values)."""
    return np.asarray(counts, dtype=float) * RAD_PER_COUNT


def rad_to_counts(rad: ArrayLike) -> np.ndarray:
    """Encoder counts (int16, rounded) for joint positions in rad; raises if out of range."""
    counts = np.rint(np.asarray(rad, dtype=float) / RAD_PER_COUNT)
    if not np.all(np.isfinite(counts)) or np.any(counts < _INT16.min) or np.any(
        counts > _INT16.max
    ):
        raise DexdrakeError(
            f"joint position(s) {rad} outside the int16 encoder range "
            f"(+-{_INT16.max * RAD_PER_COUNT:.3f} rad)"
        )
    return counts.astype(np.int16)


def normalised_torque_to_pwm(tau: ArrayLike, scale: float = PWM_SCALE_12V) -> np.ndarray:
    """PWM duty (float) for normalised torques: pwm = tau * scale (1200 on v4 at 12 V)."""
    return np.asarray(tau, dtype=float) * scale


def pwm_to_normalised_torque(pwm: ArrayLike, scale: float = PWM_SCALE_12V) -> np.ndarray:
    """Normalised torques for PWM duties (inverse of normalised_torque_to_pwm)."""
    return np.asarray(pwm, dtype=float) / scale


def saturate_pwm(pwm: ArrayLike) -> np.ndarray:
    """The 16 PWM duties (bus order) clipped to PWM_LIMITS and rounded to int16."""
    pwm = np.asarray(pwm, dtype=float)
    if pwm.shape != (NUM_JOINTS,):
        raise DexdrakeError(f"expected {NUM_JOINTS} PWM values in bus order, got {pwm.shape}")
    if not np.all(np.isfinite(pwm)):
        raise DexdrakeError(f"non-finite PWM command {pwm}")
    return np.rint(np.clip(pwm, -PWM_LIMITS, PWM_LIMITS)).astype(np.int16)


def decode_position_payload(payload: bytes) -> np.ndarray:
    """The 4 joint positions (rad) of one finger from an 8-byte position frame payload."""
    if len(payload) != 8:
        raise DexdrakeError(f"position frame payload must be 8 bytes, got {len(payload)}")
    return counts_to_rad(np.frombuffer(payload, dtype="<i2"))


def encode_torque_payload(pwm: ArrayLike) -> bytes:
    """The 8-byte torque frame payload for one finger's 4 PWM duties (int16, LE).

    Values are rounded; they must already be within int16 (use saturate_pwm first).
    """
    pwm = np.rint(np.asarray(pwm, dtype=float))
    if pwm.shape != (JOINTS_PER_FINGER,):
        raise DexdrakeError(f"a torque frame carries {JOINTS_PER_FINGER} values, got {pwm.shape}")
    if not np.all(np.isfinite(pwm)) or np.any(np.abs(pwm) > _INT16.max):
        raise DexdrakeError(f"PWM values {pwm} do not fit int16")
    return pwm.astype("<i2").tobytes()
