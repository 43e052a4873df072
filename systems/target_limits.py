"""The drivers' set-point path and overspeed trip, modelled in simulation.

On the robot a joint set-point never reaches the PD loop as commanded: the Allegro and Z1
drivers clamp it into the joint limits and then follow it at no more than a target rate
(Allegro `max_target_rate`, Z1 `max_velocity`; hardware/safety.py JointLimits and
RateLimiter); the Z1 client follows each new target evenly over the control period at no
more than that (`command_period_s`, hardware/safety.py paced_rate) and sends the reference's
own velocity with it as the controller's desired velocity where its `velocity_feedforward`
is on (hardware/z1_udp.py), while the Allegro driver's PD has no velocity set-point. A
policy whose set-points jump (closing the hand in one control step) meets a slower hand on
hardware than in an unlimited simulation, and an arm PD given no desired velocity lags its
ramp by kd/kp * velocity (0.1 rad at pi rad/s with the Z1's gains) where one given it does
not. The sim station, training's included, passes its commands through `TargetLimiter` with
the same limits, rates, pacing and velocity feed-forward, resolved from the scenario's driver entries exactly
as the drivers resolve them (`target_limits`), so that training, simulation and
hardware-in-the-loop agree.

The drivers also stop on a joint that moves too fast (a hand striking the table): the Z1
client on a reported joint velocity above its `max_measured_velocity` times
(1 + OVERSPEED_TOLERANCE), the Allegro driver on a joint's mean speed over a
`velocity_window_s` window above the same bound. `OverspeedMonitor` applies both rules to
the simulated joints (`overspeed_limits`) and ends the episode with the drivers' fault, so
that a policy trained in simulation meets the fault hardware would raise.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
from pydrake.systems.framework import Context, DiscreteValues, LeafSystem

from dexdrake.errors import StationFault
from dexdrake.hands.description import HandDescription
from dexdrake.hardware.safety import OVERSPEED_TOLERANCE, paced_rate, rate_limited
from dexdrake.hardware.z1_model import NUM_ARM_JOINTS
from dexdrake.systems.scenario import Scenario, driver_configs


def _driver_settings(scenario: Scenario, hand: HandDescription) -> tuple | None:
    """(Allegro config, its settings, Z1 config, its settings) of the scenario's drivers, or
    None for a hand without the Allegro-on-Z1 layout (no drivers)."""
    if hand.hardware_joints is None or len(hand.arm_joints) != NUM_ARM_JOINTS:
        return None
    from dexdrake.hardware.allegro_can import check_allegro_config
    from dexdrake.hardware.z1_udp import check_z1_config

    hand_cfg, arm_cfg = driver_configs(scenario)
    return hand_cfg, check_allegro_config(hand_cfg), arm_cfg, check_z1_config(arm_cfg)


class TargetLimits(NamedTuple):
    """Per joint in policy order, as the drivers apply them: the target's limits, its rate
    limit (units/s; inf: none), whether its velocity is fed forward, whether a new target is
    followed evenly over the control period (`paced`; else at the limit)."""

    lower: np.ndarray
    upper: np.ndarray
    max_rate: np.ndarray
    velocity_feedforward: np.ndarray
    paced: np.ndarray


def target_limits(scenario: Scenario, hand: HandDescription) -> TargetLimits:
    """The drivers' TargetLimits of `scenario` for `hand`.

    For the Allegro-on-Z1 layout: the Z1 driver's limits and `max_velocity` on the arm
    joints, paced where the Z1 config's `command_period_s` is set, with the reference's
    velocity where its `velocity_feedforward` is on; the Allegro driver's limits and
    `max_target_rate` on the fingers (defaults and checks of hardware/allegro_can.py and
    hardware/z1_udp.py). A hand without that layout has no drivers: its model's joint
    limits, no rate limit (inf), no velocity feed-forward, no pacing."""
    lower, upper = hand.joint_limits()
    n_arm = len(hand.arm_joints)
    feedforward, paced = np.zeros(hand.num_actuators, bool), np.zeros(hand.num_actuators, bool)
    drivers = _driver_settings(scenario, hand)
    if drivers is None:
        return TargetLimits(lower, upper, np.full(hand.num_actuators, np.inf), feedforward, paced)
    hand_cfg, hs, arm_cfg, zs = drivers
    perm = hand.hardware_permutation()  # bus joint k is policy joint perm[k]
    lower, upper, rate = lower.copy(), upper.copy(), np.empty(hand.num_actuators)
    lower[:n_arm], upper[:n_arm], rate[:n_arm] = zs.lower, zs.upper, zs.max_velocity
    lower[perm], upper[perm], rate[perm] = hs.lower, hs.upper, hand_cfg.max_target_rate
    feedforward[:n_arm] = arm_cfg.velocity_feedforward
    paced[:n_arm] = arm_cfg.command_period_s is not None
    return TargetLimits(lower, upper, rate, feedforward, paced)


class TargetLimiter(LeafSystem):
    """Inputs "command" (n set-points) and "hand_state" ([q; v], 2n); outputs "target" (n):
    the command clamped into [lower, upper] and followed at no more than `max_rate` (per
    joint, units/s), updated every `period`; on the `paced` joints a new command is followed
    at the rate that reaches it in `command_period` (paced_rate, at most `max_rate`); and
    "desired_state" ([target; v], 2n): v the target's velocity over the last period on the
    joints of `velocity_feedforward`, else 0. It starts at the measured position (clamped),
    at rest, as the drivers do when their loops start."""

    def __init__(self, limits: TargetLimits, period: float, command_period: float):
        super().__init__()
        self.lower, self.upper = np.asarray(limits.lower, float), np.asarray(limits.upper, float)
        self.max_rate, self.period, self.command_period = np.asarray(limits.max_rate, float), period, command_period
        self.feedforward = np.asarray(limits.velocity_feedforward, bool)
        self.paced = np.asarray(limits.paced, bool)
        n = self._n = len(self.lower)
        self._at_rest = np.zeros(n)  # the desired velocity without feed-forward
        self._any_paced, self._any_feedforward = bool(self.paced.any()), bool(self.feedforward.any())
        self._command = self.DeclareVectorInputPort("command", n)
        self._hand = self.DeclareVectorInputPort("hand_state", 2 * n)
        # [target; its velocity; the last command (clamped); the rate toward it]
        self.DeclareDiscreteState(4 * n)
        self.DeclareVectorOutputPort("target", n, lambda c, out: out.SetFromVector(c.get_discrete_state(0).value()[:n]),
                                     {self.xd_ticket()})
        self.DeclareVectorOutputPort("desired_state", 2 * n,
                                     lambda c, out: out.SetFromVector(c.get_discrete_state(0).value()[: 2 * n]),
                                     {self.xd_ticket()})
        self.DeclareInitializationDiscreteUpdateEvent(self._start)
        self.DeclarePeriodicDiscreteUpdateEvent(period, 0.0, self._update)

    def _start(self, context: Context, state: DiscreteValues) -> None:
        q = np.clip(self._hand.Eval(context)[: len(self.lower)], self.lower, self.upper)
        state.set_value(0, np.r_[q, np.zeros(len(q)), q, self.max_rate])

    def _update(self, context: Context, state: DiscreteValues) -> None:
        n = self._n
        target = np.minimum(np.maximum(self._command.Eval(context), self.lower), self.upper)
        x = context.get_discrete_state(0).value()
        previous, last, rate = x[:n], x[2 * n:3 * n], x[3 * n:]
        if self._any_paced and not np.array_equal(target, last):
            rate = np.where(self.paced, paced_rate(previous, target, self.max_rate, self.command_period), self.max_rate)
        q = rate_limited(previous, target, rate, self.period)
        v = np.where(self.feedforward, (q - previous) / self.period, 0.0) if self._any_feedforward else self._at_rest
        state.set_value(0, np.concatenate((q, v, target, rate)))


def overspeed_limits(scenario: Scenario, hand: HandDescription) -> tuple[np.ndarray, np.ndarray] | None:
    """(speed, window) per joint in policy order, as the drivers trip: a joint faster than
    `speed` (rad/s: `max_measured_velocity` x (1 + OVERSPEED_TOLERANCE)) is a fault, its
    velocity taken as measured (window 0: the Z1's reported velocity) or as the mean over
    `window` seconds (the Allegro's `velocity_window_s`). None without drivers."""
    drivers = _driver_settings(scenario, hand)
    if drivers is None:
        return None
    hand_cfg, hs, _, zs = drivers
    n_arm, perm = len(hand.arm_joints), hand.hardware_permutation()
    speed, window = np.empty(hand.num_actuators), np.zeros(hand.num_actuators)
    speed[:n_arm] = zs.max_measured_velocity
    speed[perm], window[perm] = hs.max_measured_velocity, hand_cfg.velocity_window_s
    return speed * (1 + OVERSPEED_TOLERANCE), window


class OverspeedMonitor(LeafSystem):
    """Input "hand_state" ([q; v], 2n), checked every `period`: StationFault when a joint of
    window 0 has |v| above its `speed`, or a windowed joint's mean speed |q - q0| / (t - t0)
    over its last window (at least `window` long; windows follow each other) is above it.
    Its joint names and speeds are the drivers' (`overspeed_limits`)."""

    def __init__(self, speed: np.ndarray, window: np.ndarray, period: float, names: list[str]):
        super().__init__()
        self.speed, self.window, self.names = np.asarray(speed, float), np.asarray(window, float), names
        self._instant = self.window == 0
        n = self._n = len(self.speed)
        self._hand = self.DeclareVectorInputPort("hand_state", 2 * n)
        self.DeclareDiscreteState(2 * n)  # [q at each joint's window start; that start's time]
        self.DeclareInitializationDiscreteUpdateEvent(self._start)
        self.DeclarePeriodicDiscreteUpdateEvent(period, 0.0, self._update)

    def _start(self, context: Context, state: DiscreteValues) -> None:
        n = len(self.speed)
        state.set_value(0, np.r_[self._hand.Eval(context)[:n], np.full(n, context.get_time())])

    def _update(self, context: Context, state: DiscreteValues) -> None:
        n, t = self._n, context.get_time()
        x = self._hand.Eval(context)
        q, v = x[:n], x[n:]
        s = context.get_discrete_state(0).value()
        q0, t0 = s[:n], s[n:]
        span = t - t0
        due = ~self._instant & (span >= self.window - 1e-9)
        measured = np.where(self._instant, np.abs(v), np.where(due, np.abs(q - q0) / np.maximum(span, 1e-9), 0.0))
        over = measured > self.speed
        if over.any():
            j = int(np.argmax(over))
            raise StationFault(f"overspeed: {self.names[j]} at {measured[j]:.2f} rad/s (the driver trips above "
                               f"{self.speed[j]:.2f} rad/s) at t = {t:.3f} s")
        state.set_value(0, np.concatenate((np.where(due, q, q0), np.where(due, t, t0))))
