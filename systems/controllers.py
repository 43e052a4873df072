"""The controllers of the diagram's slot (systems/diagram.py): the scenario's torch policy
(PolicySystem and the map of its normalised actions to joint set-points), the scripted grasp
and the expert (ReactiveGrasp) (env controllers driven by the station's measurements through a
mirroring GraspEnv). Every one outputs "command" and reads some of "features",
"hand_state" and "object_pose"."""

from __future__ import annotations

import sys
from collections.abc import Callable

import numpy as np
from pydrake.systems.framework import Diagram, DiagramBuilder
from pydrake.systems.primitives import PassThrough

from dexdrake.errors import DexdrakeError
from dexdrake.hands.action_map import ActionMap
from dexdrake.hands.description import HandDescription, load_hand
from dexdrake.systems.grasp_env import GraspEnv
from dexdrake.systems.reactive_grasp import ReactiveGrasp
from dexdrake.systems.scenario import Scenario, simulated
from dexdrake.systems.scenario_record import check_policy_scenario
from dexdrake.systems.scripted_grasp import ScriptedGrasp, script_for
from dexdrake.systems.station import ControllerSystem, pose_from_vector


def _stderr(line: str) -> None:
    print(line, file=sys.stderr)


def policy_controller(scenario: Scenario, hand: HandDescription, allow_scenario_mismatch: bool = False,
                      warn: Callable[[str], None] = _stderr) -> tuple[Diagram, str]:
    """The scenario's policy in the slot: PolicySystem (features -> normalised action -> joint
    set-points, by the policy's arm action); refused (a DexdrakeError naming the checkpoint and the
    reason) when the checkpoint is missing or unreadable, or was trained for another hand,
    feature set or action size, or under another plant step or control period (its
    recorded scenario, `check_policy_scenario`; `allow_scenario_mismatch` runs it anyway).
    Warning lines go to `warn`."""
    from dexdrake.learn.policy import check_policy_fits, load_policy
    from dexdrake.paths import resolve_model_path
    from dexdrake.systems.policy_system import PolicySystem

    entry = scenario.policy
    try:
        policy, metadata = load_policy(resolve_model_path(entry.checkpoint))
    except DexdrakeError as err:
        raise DexdrakeError(f"policy refused: {err}") from None
    cfg = policy.config
    try:
        check_policy_fits(cfg, scenario.hand, entry.feature_set, entry.checkpoint)
    except DexdrakeError as err:
        raise DexdrakeError(f"policy refused: {err}") from None
    for line in check_policy_scenario(metadata["scenario"], scenario, entry.checkpoint, allow_scenario_mismatch):
        warn(line)
    n = hand.num_actuators
    builder = DiagramBuilder()
    system = builder.AddNamedSystem("policy_system", PolicySystem(policy, scenario.control_period,
                                                                  actions=ActionMap(hand, cfg.arm_action)))
    hand_state = builder.AddNamedSystem("hand_state", PassThrough(2 * n))
    builder.ExportInput(hand_state.get_input_port(), "hand_state")
    builder.Connect(hand_state.get_output_port(), system.GetInputPort("hand_state"))
    builder.ExportInput(system.GetInputPort("observation"), "features")
    builder.ExportInput(builder.AddNamedSystem("object_pose", PassThrough(7)).get_input_port(), "object_pose")
    builder.ExportOutput(system.GetOutputPort("command"), "command")
    description = (f"policy {entry.checkpoint} (hand {cfg.hand}, feature set {cfg.feature_set}, "
                   f"{cfg.obs_dim} observations -> {cfg.action_dim} actions, arm by {cfg.arm_action}, "
                   f"stage {metadata.get('stage', 'unknown')})")
    slot = builder.Build()
    slot.set_name("policy")
    return slot, description


class OnMeasurements:
    """An env controller (`make(env)` once, then `controller(env) -> set-points`: the
    scripted grasp, the expert (ReactiveGrasp)) driven by the station's measurements, as a
    ControllerSystem callback: a GraspEnv without features mirrors the measured hand state
    and the perceived object pose (the scripted grasp plans on the first one); the env's
    clock starts at the first call."""

    def __init__(self, scenario: Scenario, make: Callable):
        self.env = GraspEnv(simulated(scenario), feature_set=None, horizon=1)
        self.env.reset(scenario.seed)
        self._make, self._controller, self._t0 = make, None, 0.0

    def __call__(self, t: float, hand_state: np.ndarray, object_pose: np.ndarray) -> np.ndarray:
        env = self.env
        env.mirror(hand_state, pose_from_vector(object_pose))
        if self._controller is None:
            self._t0 = t
            self._controller = self._make(env)
        env.context.SetTime(t - self._t0)
        return self._controller(env)


def describe_script(hand: HandDescription) -> str:
    """The scripted grasp's plan, from the GraspScript the hand description configures."""
    g = script_for(hand)
    return (f"scripted grasp (no policy in the scenario): from the first perceived pose, approach "
            f"{g.hover:.2f} m above the object by {g.approach_end:.1f} s, descend by {g.descend_end:.1f} s, "
            f"close by {g.close_end:.1f} s, lift {g.lift:.2f} m by {g.lift_end:.1f} s")


def make_controller(scenario: Scenario, allow_scenario_mismatch: bool = False,
                    warn: Callable[[str], None] = _stderr):
    """(controller slot system, description) of what the scenario asks for: its policy (a
    policy that cannot be run is refused with a DexdrakeError, never replaced;
    `policy_controller`), or the scripted grasp when the scenario names no policy."""
    hand = load_hand(scenario.hand)
    if scenario.policy is not None:
        return policy_controller(scenario, hand, allow_scenario_mismatch, warn)
    system = ControllerSystem(OnMeasurements(scenario, ScriptedGrasp), hand, scenario.control_period)
    return system, describe_script(hand)


def expert_controller(scenario: Scenario) -> ControllerSystem:
    """The expert (systems/reactive_grasp.ReactiveGrasp) in the slot."""
    return ControllerSystem(OnMeasurements(scenario, ReactiveGrasp), load_hand(scenario.hand), scenario.control_period)
