"""The drivers' set-point limits, modelled in simulation.

On the robot a joint set-point never reaches the PD loop as commanded: the Allegro and Z1
drivers clamp it into the joint limits and then follow it at no more than a target rate
(Allegro `max_target_rate`, Z1 `max_velocity`; hardware/safety.py JointLimits and
RateLimiter). A policy whose set-points jump (closing the hand in one control step) meets a
slower hand on hardware than in an unlimited simulation. The station's sim mode passes its
commands through `TargetLimiter` with the same limits and rates, resolved from the
scenario's driver entries exactly as the drivers resolve them (`target_limits`), so that
simulation and hardware-in-the-loop agree.
"""

from __future__ import annotations

import numpy as np
from pydrake.systems.framework import Context, DiscreteValues, LeafSystem

from dexdrake.hands.description import HandDescription
from dexdrake.hardware.safety import rate_limited
from dexdrake.hardware.z1_model import NUM_ARM_JOINTS
from dexdrake.systems.scenario import Scenario, driver_configs


def target_limits(scenario: Scenario, hand: HandDescription) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(lower, upper, max_rate) per joint in policy order, as the drivers apply them.

    For the Allegro-on-Z1 layout: the Z1 driver's limits and `max_velocity` on the arm
    joints, the Allegro driver's limits and `max_target_rate` on the fingers (defaults and
    checks of hardware/allegro_can.py and hardware/z1_udp.py). A hand without that layout
    has no drivers: its model's joint limits and no rate limit (inf)."""
    lower, upper = hand.joint_limits()
    n_arm = len(hand.arm_joints)
    if hand.hardware_joints is None or n_arm != NUM_ARM_JOINTS:
        return lower, upper, np.full(hand.num_actuators, np.inf)
    from dexdrake.hardware.allegro_can import check_allegro_config
    from dexdrake.hardware.z1_udp import check_z1_config

    hand_cfg, arm_cfg = driver_configs(scenario)
    hs, zs = check_allegro_config(hand_cfg), check_z1_config(arm_cfg)
    perm = hand.hardware_permutation()  # bus joint k is policy joint perm[k]
    lower, upper, rate = lower.copy(), upper.copy(), np.empty(hand.num_actuators)
    lower[:n_arm], upper[:n_arm], rate[:n_arm] = zs.lower, zs.upper, zs.max_velocity
    lower[perm], upper[perm], rate[perm] = hs.lower, hs.upper, hand_cfg.max_target_rate
    return lower, upper, rate


class TargetLimiter(LeafSystem):
    """Inputs "command" (n set-points) and "hand_state" ([q; v], 2n); output "target" (n):
    the command clamped into [lower, upper] and followed at no more than `max_rate` (per
    joint, units/s), updated every `period`. It starts at the measured position (clamped),
    as the drivers do when their loops start."""

    def __init__(self, lower: np.ndarray, upper: np.ndarray, max_rate: np.ndarray, period: float):
        super().__init__()
        self.lower, self.upper = np.asarray(lower, float), np.asarray(upper, float)
        self.max_rate, self.period = np.asarray(max_rate, float), period
        n = len(self.lower)
        self._command = self.DeclareVectorInputPort("command", n)
        self._hand = self.DeclareVectorInputPort("hand_state", 2 * n)
        state = self.DeclareDiscreteState(n)
        self.DeclareStateOutputPort("target", state)
        self.DeclareInitializationDiscreteUpdateEvent(self._start)
        self.DeclarePeriodicDiscreteUpdateEvent(period, 0.0, self._update)

    def _start(self, context: Context, state: DiscreteValues) -> None:
        q = self._hand.Eval(context)[: len(self.lower)]
        state.set_value(0, np.clip(q, self.lower, self.upper))

    def _update(self, context: Context, state: DiscreteValues) -> None:
        target = np.clip(self._command.Eval(context), self.lower, self.upper)
        state.set_value(0, rate_limited(context.get_discrete_state(0).value(), target,
                                        self.max_rate, self.period))
