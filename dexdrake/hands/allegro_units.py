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

NUM_JOINTS = 16  # joint names in bus order: the hand description's `hardware_joints`

#: rad per encoder count: rad = counts * 333.3 / 65536 * pi / 180 (about 8.876e-5).
#: The manual's printed formula is wrong; every working driver uses this one.
RAD_PER_COUNT = 333.3 / 65536 * math.pi / 180

#: PWM duty for a normalised torque of 1: 1200 on v4 at 12 V (v3 at 8 V: 800; 24 V: 500).
PWM_SCALE_12V = 1200.0

#: ASSUMPTION, the one place it is made: joint torque per PWM count (N*m). The vendor does
#: not document the PWM -> N*m mapping (max motor torque 0.70 N*m, gearing 1:369); full PWM
#: 1200 is taken as 6 N*m. The simulated hand's PD gains are the vendor gains times this
#: (scripts/build_allegro_models.py) and the HIL world turns PWM into joint torque with it
#: (systems/scenario.HilWorldConfig.pwm_torque_scale multiplies it; `dexdrake parity`
#: reports HIL success at 0.5x, 1x and 2x).
NM_PER_PWM = 6.0 / PWM_SCALE_12V

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
