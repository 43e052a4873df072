"""The record of the scenario a policy was trained under, stored in its checkpoint, and the
check of it against the scenario the policy is about to run under."""

from __future__ import annotations

import dataclasses
import math
from typing import Any

from dexdrake.hands.description import load_hand
from dexdrake.objects.mass import ObjectMass
from dexdrake.objects.meshfile import file_hash
from dexdrake.perceived_pose import PerceptionModel
from dexdrake.systems.scenario import Scenario, ScenarioError
from dexdrake.systems.target_limits import overspeed_limits, target_limits


def scenario_record(s: Scenario) -> dict[str, Any]:
    """What a policy trained or run under `s` depends on, as plain data (stored in policy
    checkpoints): the plant step and control period (s), the plant's contact approximation,
    the drivers' target limits in policy order (systems/target_limits.py TargetLimits: lower,
    upper, max_rate (inf: none), velocity_feedforward, paced) and overspeed trip (speed,
    window; None without drivers), the perception model the features see the object pose through
    (dexdrake/perceived_pose.py), the camera's depth noise (rendered cameras only), the sha256
    of the hand's model file (its geometry, masses and drive) and what the objects weigh in the
    hand's scenes (its description's `object_mass`, dexdrake/objects/mass.py)."""
    hand = load_hand(s.hand)
    limits = target_limits(s, hand)
    overspeed = overspeed_limits(s, hand)
    return {"time_step": s.time_step, "control_period": s.control_period,
            "contact_approximation": s.contact_approximation,
            "target_limits": {key: value.tolist() for key, value in limits._asdict().items()},
            "overspeed": None if overspeed is None else {"speed": overspeed[0].tolist(),
                                                         "window": overspeed[1].tolist()},
            "perception": dataclasses.asdict(s.perception),
            "depth_noise": s.drivers.camera.kind == "rendered" and s.drivers.camera.depth_noise,
            "hand_model": file_hash(hand.model_path),
            "object_mass": dataclasses.asdict(hand.object_mass)}


def check_policy_scenario(trained: dict[str, Any], s: Scenario, checkpoint: str,
                          allow_mismatch: bool = False) -> list[str]:
    """Compare the scenario a policy was trained under (`trained`, its checkpoint's
    `scenario_record`) with `s`, the one it is about to run under. A different plant step or
    control period raises ScenarioError (one line) unless `allow_mismatch`; returns the
    warning lines to print: those overridden mismatches, and a difference in the target
    limits, the overspeed trip (a record without one was trained without it), the contact
    approximation (a record without one: "sap"), the perception model (which the policy
    may tolerate; a record without one was trained on the exact pose), the hand's model file
    (where recorded) or the objects' masses (a record without them: the paper's 0.5 kg)."""
    run = scenario_record(s)
    hard = [f"{key} {trained[key] * 1e3:g} ms (this scenario: {run[key] * 1e3:g} ms)"
            for key in ("time_step", "control_period") if not math.isclose(trained[key], run[key], rel_tol=1e-9)]
    if hard and not allow_mismatch:
        raise ScenarioError(f"policy refused: {checkpoint} was trained under {'; '.join(hard)}; "
                            "--allow-scenario-mismatch runs it anyway")
    warnings = [f"warning: {checkpoint} was trained under {h}; running it anyway (--allow-scenario-mismatch)"
                for h in hard]
    if trained.get("target_limits") is None:
        warnings.append(f"warning: {checkpoint} was trained without the drivers' target limits; "
                        "this scenario limits its set-points")
    elif trained["target_limits"] != run["target_limits"]:
        warnings.append(f"warning: {checkpoint} was trained under other target limits or rates "
                        "than this scenario's drivers apply")
    if trained.get("overspeed") is None and run["overspeed"] is not None:
        warnings.append(f"warning: {checkpoint} was trained without the drivers' overspeed trip; "
                        "this scenario's drivers stop on it")
    elif trained.get("overspeed") != run["overspeed"]:
        warnings.append(f"warning: {checkpoint} was trained under another overspeed trip "
                        "than this scenario's drivers apply")
    if trained.get("contact_approximation", "sap") != run["contact_approximation"]:
        warnings.append(f"warning: {checkpoint} was trained under the {trained.get('contact_approximation', 'sap')!r} "
                        f"contact approximation; this scenario's plant uses {run['contact_approximation']!r}")
    if trained.get("perception", dataclasses.asdict(PerceptionModel())) != run["perception"]:
        warnings.append(f"warning: {checkpoint} was trained under another perception model (pose noise, "
                        f"frame period, latency) than this scenario's: {trained.get('perception')}")
    if trained.get("hand_model", run["hand_model"]) != run["hand_model"]:
        warnings.append(f"warning: {checkpoint} was trained on another model of the {s.hand} hand (sha256 "
                        f"{trained['hand_model'][:12]}; its model file now: {run['hand_model'][:12]})")
    masses = trained.get("object_mass", dataclasses.asdict(ObjectMass()))
    if masses != run["object_mass"]:
        warnings.append(f"warning: {checkpoint} was trained with other object masses ({masses}) than this "
                        f"hand's scenes give them ({run['object_mass']})")
    return warnings
