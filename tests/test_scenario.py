"""The Scenario as the one configuration: packaged files, one plant step, the drivers' limits
in training, the scenario recorded in checkpoints and checked at load, faults as types."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from dexdrake.cli import main
from dexdrake.learn.policy import UNRECORDED_SCENARIO, DexRepNetPolicy, PolicyConfig, load_policy, save_policy
from dexdrake.systems.env_factory import GraspEnvFactory, training_scenario
from dexdrake.systems.scenario import (Scenario, ScenarioError, load_scenario, packaged_scenarios, scenario_path,
                                       validate_scenario)
from dexdrake.systems.scenario_record import check_policy_scenario, scenario_record
from dexdrake.systems.scene import ObjectPlacement

REPO = Path(__file__).resolve().parents[1]


def test_packaged_scenarios_resolve_from_any_folder_and_a_path_stays_a_path(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    assert packaged_scenarios() == ["hil", "real", "real_emulated", "real_emulated_world", "sim"]
    assert {name: load_scenario(name).mode for name in packaged_scenarios()} == {
        "hil": "hil", "real": "real", "real_emulated": "real", "real_emulated_world": "real", "sim": "sim"}
    assert scenario_path("configs/hil.yaml") == Path("configs/hil.yaml")
    with pytest.raises(ScenarioError, match="configs/hil.yaml does not exist"):
        load_scenario("configs/hil.yaml")
    (tmp_path / "hil").write_text("not read: a bare packaged name wins")  # names the packaged one
    assert load_scenario("hil").mode == "hil"


def test_every_mode_steps_its_plant_at_5_ms_and_controls_at_20_ms():
    scenarios = [Scenario(), training_scenario("adroit")] + [load_scenario(n) for n in packaged_scenarios()]
    assert {(s.time_step, s.control_period) for s in scenarios} == {(0.005, 0.02)}
    env = GraspEnvFactory("adroit", None, ("sphere_medium",), horizon=2)()
    assert env.scene.plant.time_step() == 0.005 and env.scenario.control_period == 0.02


def test_training_steps_the_station_with_the_drivers_target_limits():
    env = GraspEnvFactory("allegro_z1", None, ("box_cube",), horizon=3)()
    assert env.built.station.diagram.HasSubsystemNamed("driver_target_limits")
    lower, upper = env.scene.hand.joint_limits()
    rate = np.asarray(scenario_record(env.scenario)["target_limits"]["max_rate"])
    env.reset(0)
    q0 = env.hand_state()[: env.action_dim]
    far = np.where(q0 - lower > upper - q0, lower, upper)  # the farther limit of every joint
    env.step_positions(far)
    moved = np.abs(env.hand_state()[: env.action_dim] - q0)
    assert np.all(moved <= rate * env.scenario.control_period + 1e-3), moved / env.scenario.control_period


def test_the_packaged_allegro_z1_scenarios_limit_targets_as_training_does():
    """hil and real deploy a policy under the limits it was trained under: the Z1's targets at
    2 rad/s (below its pi rad/s limit, so that a lunge's impact stays under the overspeed trip),
    the Allegro's at 3 rad/s."""
    trained = scenario_record(training_scenario("allegro_z1"))["target_limits"]
    assert set(trained["max_rate"]) == {2.0, 3.0}
    for name in packaged_scenarios():
        scenario = load_scenario(name)
        if scenario.hand == "allegro_z1":
            assert scenario_record(scenario)["target_limits"] == trained, name


def test_a_checkpoint_records_its_scenario_and_one_without_loads_as_the_shipped_weights(tmp_path):
    policy = DexRepNetPolicy(PolicyConfig.from_blocks({"hand": 4}, 2, hand="adroit", feature_set="Hand2obj"))
    record = scenario_record(training_scenario("adroit"))
    _, meta = load_policy(save_policy(tmp_path / "with.pt", policy, {"scenario": record}))
    assert meta["scenario"] == record and record["time_step"] == 0.005 and record["target_limits"] is not None
    _, meta = load_policy(save_policy(tmp_path / "without.pt", policy))
    assert meta["scenario"] == UNRECORDED_SCENARIO
    _, shipped = load_policy(REPO / "models" / "weights" / "adroit_dexrep_policy.pt")
    assert shipped["scenario"] == {"time_step": 0.005, "control_period": 0.02, "target_limits": None,
                                   "depth_noise": False}


def test_a_policy_trained_under_another_step_or_period_is_refused_unless_allowed():
    hil = load_scenario("hil")
    trained = scenario_record(hil)
    assert check_policy_scenario(trained, hil, "p.pt") == []
    for field, value in (("time_step", 0.002), ("control_period", 0.04)):
        other = replace(hil, **{field: value})
        with pytest.raises(ScenarioError, match=f"p.pt was trained under {field}") as err:
            check_policy_scenario(trained, other, "p.pt")
        assert len(str(err.value).splitlines()) == 1 and "--allow-scenario-mismatch" in str(err.value)
        (warning,) = check_policy_scenario(trained, other, "p.pt", allow_mismatch=True)
        assert warning.startswith("warning: p.pt was trained under") and "running it anyway" in warning
    assert "without the drivers' target limits" in check_policy_scenario(UNRECORDED_SCENARIO, hil, "p.pt")[0]


def test_a_policy_trained_on_another_model_of_the_hand_is_warned():
    hil = load_scenario("hil")
    trained = {**scenario_record(hil), "hand_model": "0" * 64}
    (warning,) = check_policy_scenario(trained, hil, "p.pt")
    assert "p.pt was trained on another model of the allegro_z1 hand (sha256 000000000000;" in warning


def test_a_policy_records_the_drivers_overspeed_trip_and_is_warned_without_it():
    hil = load_scenario("hil")
    trained = scenario_record(hil)
    assert len(trained["overspeed"]["speed"]) == len(trained["overspeed"]["window"]) == 22
    (warning,) = check_policy_scenario({**trained, "overspeed": None}, hil, "p.pt")
    assert "p.pt was trained without the drivers' overspeed trip" in warning
    slower = {**trained, "overspeed": {**trained["overspeed"], "window": [0.0] * 22}}
    assert "under another overspeed trip" in check_policy_scenario(slower, hil, "p.pt")[0]
    assert scenario_record(training_scenario("adroit"))["overspeed"] is None  # no drivers


def test_the_plant_uses_the_scenarios_contact_approximation_and_a_policy_records_it():
    from pydrake.multibody.plant import DiscreteContactApproximation

    from dexdrake.systems.grasp_env import GraspEnv

    lagged = replace(training_scenario("adroit", "sphere_medium"), contact_approximation="lagged")
    env = GraspEnv(lagged, horizon=2)
    assert env.scene.plant.get_discrete_contact_approximation() == DiscreteContactApproximation.kLagged
    with pytest.raises(ScenarioError, match="contact_approximation 'tamsi' is not one of sap, similar, lagged"):
        validate_scenario(replace(lagged, contact_approximation="tamsi"))
    hil = load_scenario("hil")
    assert scenario_record(hil)["contact_approximation"] == "sap"
    (warning,) = check_policy_scenario(scenario_record(hil), replace(hil, contact_approximation="similar"), "p.pt")
    assert "trained under the 'sap' contact approximation" in warning and "'similar'" in warning
    unrecorded = {k: v for k, v in scenario_record(hil).items() if k != "contact_approximation"}
    assert check_policy_scenario(unrecorded, hil, "p.pt") == []  # a record without one: sap


def test_the_plant_weighs_the_object_as_the_hands_description_says_and_a_policy_records_it():
    from dexdrake.hands.description import load_hand
    from dexdrake.objects.library import get_object
    from dexdrake.systems.scene import build_grasp_scene

    for hand, name in (("allegro_z1", "knife_small"), ("allegro_z1", "bottle_water"), ("adroit", "bottle_water")):
        scene = build_grasp_scene(training_scenario(hand, name))
        body = scene.plant.GetBodyByName(name, scene.object_instance)
        expected = get_object(name).mass(load_hand(hand).object_mass)
        assert body.default_mass() == pytest.approx(expected), (hand, name)
    assert scenario_record(training_scenario("adroit"))["object_mass"]["density"] is None  # the paper's 0.5 kg
    hil = load_scenario("hil")
    trained = scenario_record(hil)
    assert trained["object_mass"]["density"] == 500.0
    unrecorded = {k: v for k, v in trained.items() if k != "object_mass"}  # trained before masses: the paper's
    (warning,) = check_policy_scenario(unrecorded, hil, "p.pt")
    assert "p.pt was trained with other object masses" in warning and "'density': None" in warning


def test_sim_runs_a_scenarios_station_from_any_folder(tmp_path, monkeypatch, capsys):
    from rrd_content import logged_rows

    monkeypatch.chdir(tmp_path)
    assert main(["sim", "--config", "sim", "--controller", "scripted", "--horizon", "3", "--rrd", "sim.rrd"]) == 0
    out = capsys.readouterr().out
    assert "sim: box_cube seed=0 controller=scripted grasp" in out and "steps=3" in out
    rows = logged_rows(tmp_path / "sim.rrd")  # every control step recorded from the station's ports
    assert rows["/world/object"] >= 3 and any(e.startswith("/joints/") for e in rows)
    assert main(["sim", "--config", "sim", "--time-step", "0.002", "--horizon", "1"]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "trained under time_step 5 ms (this scenario: 2 ms)" in err


def test_an_episode_starts_from_the_one_reset_of_its_seed():
    env = GraspEnvFactory("adroit", None, ("sphere_medium",), horizon=2)()
    for seed in (0, 7):
        env.reset(seed)
        expected = ObjectPlacement.from_seed(seed).pose(env.scene.object_info)
        assert env.object_pose().IsNearlyEqualTo(expected, 1e-9)
        np.testing.assert_array_equal(env.hand_state()[: env.action_dim], env.scene.hand.pregrasp_vector())


def test_station_faults_end_an_episode_by_type_and_other_errors_propagate():
    from dexdrake.systems.diagram import run_station_episode
    from dexdrake.errors import StationFault
    from dexdrake.systems.station import make_station

    scenario = replace(load_scenario("sim"), policy=None)

    def fault(t, hand_state, object_pose):
        raise StationFault("driver fault")

    def bug(t, hand_state, object_pose):
        raise RuntimeError("no default value")  # a bug whose text holds "fault"

    assert run_station_episode(make_station(scenario), fault, 2).fault == "driver fault"
    with pytest.raises(RuntimeError, match="no default value"):
        run_station_episode(make_station(scenario), bug, 2)


def test_the_envs_direct_features_equal_the_diagrams_features_port_step_by_step():
    from dexdrake.systems.scripted_grasp import ScriptedGrasp

    env = GraspEnvFactory("adroit", "DexRep", ("sphere_medium",), horizon=60)()
    port = env.diagram.GetOutputPort("features")
    compared = []

    def compare() -> None:
        direct, through_port = env.observation(), port.Eval(env.context)
        np.testing.assert_allclose(direct, through_port, rtol=0, atol=1e-12)  # the pose's round trip
        compared.append(np.abs(direct).sum())

    env.rollout(ScriptedGrasp, 0, logger=_Hooks(compare))
    assert len(compared) == 61 and len(set(compared)) > 30  # the reset, then every step, features changing


class _Hooks:
    """A logger stand-in for `GraspEnv.rollout`: `check` after the reset and every step."""

    def __init__(self, check):
        self.check = check

    def hooks(self, env):
        return {"on_reset": self.check, "on_step": lambda *args, **kwargs: self.check()}
