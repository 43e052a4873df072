"""Recordings a person can read at a glance: every mode's .rrd carries the one logger's
blueprint, and every view of it shows data the recording holds."""

from pathlib import Path

import numpy as np
import pytest
from rrd_content import blueprint_tree, logged_rows, matches, text_logs

from dexdrake.cli import main

CONFIGS = Path(__file__).resolve().parents[1] / "configs"
SEED = 1_000_000_007  # evaluation seeds lie in the range reserved for evaluation
STATION_VIEWS = {"Loop rates (Hz)", "Latencies (ms)", "Fault counters", "Faults and events"}
pytestmark = pytest.mark.usefixtures("one_torch_thread")


def _shipped(hand: str) -> str:
    from dexdrake.paths import models_dir

    return str(models_dir() / "weights" / f"{hand}_dexrep_policy.pt")


def _real(path: Path) -> None:
    """The station logger in real mode fed the measured states of a short simulated
    Allegro-on-Z1 episode, as the real loop feeds it (no world truth: the task is scored on
    the perceived pose); tests/test_real_episode.py records a real episode end to end."""
    from dexdrake.hands.description import load_hand
    from dexdrake.hardware.safety import period_stats
    from dexdrake.systems.grasp_env import GraspEnv
    from dexdrake.systems.rerun_logger import RerunLogger
    from dexdrake.systems.scenario import load_scenario, simulated
    from dexdrake.systems.scripted_grasp import ScriptedGrasp
    from dexdrake.systems.station import Station, pose_vector

    scenario = load_scenario(CONFIGS / "real.yaml")
    env = GraspEnv(simulated(scenario), horizon=3)
    logger = RerunLogger(path, "real", scenario=scenario)
    logger.attach(Station(scenario, None, load_hand(scenario.hand)))  # no devices: no device statistics
    env.reset(scenario.seed)
    controller = ScriptedGrasp(env)
    for k in range(3):
        env.step_positions(controller(env))
        times = [scenario.control_period * i for i in range(k + 2)]
        logger.log_station_step(env.context.get_time(), env.hand_state(), env.q_command,
                                pose_vector(env.scene.object_pose(env.plant_context)),
                                {**period_stats(times), "non_finite": 0, "clipped": 0})
    logger.log_fault("Allegro hand fault: watchdog (a fault as the loop reports it)")
    logger.close()


@pytest.fixture(scope="module")
def recordings(tmp_path_factory) -> dict[str, Path]:
    """One short recording per mode, each made the way its command makes it."""
    out = tmp_path_factory.mktemp("recordings")
    hil = out / "hil.yaml"
    hil.write_text((CONFIGS / "hil.yaml").read_text().replace("kind: rendered", "kind: sim"))
    commands = {
        "sim": ["sim", "--horizon", "3"],
        "eval": ["eval", "--policy", _shipped("adroit"), "--objects", "apple,mug", "--episodes-per-object", "1",
                 "--seed", str(SEED), "--horizon", "3"],
        "demo": ["demo", "--horizon", "3"],
        "hil": ["hil", "--config", str(hil), "--horizon", "3"],
    }
    paths = {}
    for mode, command in commands.items():
        paths[mode] = out / f"{mode}.rrd"
        assert main([*command, "--rrd", str(paths[mode])]) == 0, mode
    paths["real"] = out / "real.rrd"
    _real(paths["real"])
    return paths


MODES = ("sim", "eval", "demo", "hil", "real")


@pytest.mark.parametrize("mode", MODES)
def test_every_view_of_the_blueprint_shows_logged_data(recordings, mode):
    tree, rows = blueprint_tree(recordings[mode]), logged_rows(recordings[mode])
    views = tree.views()
    assert len(views) >= 10
    for view in views:
        shown = [e for e in rows if matches(view, e)]
        assert shown, f"{mode}: view {view.name!r} shows none of the logged entities"
    # and nothing logged is left out of every view (the episode list is shown where there are many)
    hidden = {"/__properties", "/world"} | ({"/episodes"} if mode != "eval" else set())
    for entity in set(rows) - hidden:
        assert any(matches(v, entity) for v in views), f"{mode}: {entity} is in no view"
    # every joint's measured and commanded position are in one plot, one plot per finger
    joints = [e.removesuffix("/q") for e in rows if e.startswith("/joints/") and e.endswith("/q")]
    assert joints and all(rows[f"{j}/q"] > 0 and rows[f"{j}/cmd"] > 0 for j in joints)
    for joint in joints:
        (plot,) = [v for v in views if matches(v, f"{joint}/q")]
        assert matches(plot, f"{joint}/cmd") and plot.origin == joint.rsplit("/", 1)[0].lstrip("/")


@pytest.mark.parametrize("mode", MODES)
def test_the_scene_is_large_and_framed_on_hand_and_object(recordings, mode):
    tree = blueprint_tree(recordings[mode])
    assert tree.kind == "horizontal" and tree.shares[0] > tree.shares[1]  # the 3D side is the wider
    tabs = tree.children[0]
    assert tabs.kind == "tabs"
    scene = tabs.children[0]  # the first tab: what the viewer opens on
    assert (scene.kind, scene.name, scene.origin) == ("3D", "Scene", "world")
    eye, target = np.array(scene.eye["position"]), np.array(scene.eye["look_target"])
    # the table is 1 m wide: an eye within 0.5 m of a target near the object frames the grasp
    assert 0.15 < np.linalg.norm(eye - target) < 0.5
    assert np.linalg.norm(target[:2]) < 0.15 and 0.0 < target[2] < 0.3
    assert matches(scene, "/world/hand/palm") and matches(scene, "/world/object")
    assert not matches(scene, "/world/dexrep/grid/voxels")  # DexRep is one tab away
    (dexrep,) = [n for n in tabs.children if n.name == "DexRep"]
    for entity in ("/world/dexrep/grid/voxels", "/world/dexrep/hand_points", "/world/dexrep/closest_points"):
        assert any(matches(v, entity) for v in dexrep.views()), entity


@pytest.mark.parametrize("mode", MODES)
def test_lift_band_reward_and_success_share_one_panel(recordings, mode):
    rows = logged_rows(recordings[mode])
    (task,) = [n for n in blueprint_tree(recordings[mode]).walk() if n.name == "Task"]
    for entity in ("/task/lift", "/task/band/low", "/task/band/high", "/reward/total", "/reward/r_d",
                   "/task/success"):
        assert rows[entity] > 0 and any(matches(v, entity) for v in task.views()), entity


def test_one_blueprint_in_every_mode_adding_only_what_the_mode_has(recordings):
    names = {mode: {v.name for v in blueprint_tree(recordings[mode]).views()} for mode in MODES}
    assert names["sim"] == names["demo"] == names["eval"] - {"Episodes"}  # the same hand (Adroit)
    assert "Episodes" in names["eval"]  # an evaluation has many episodes
    assert names["hil"] == names["real"]  # the same hand (Allegro on a Z1)
    assert names["hil"] - names["sim"] >= STATION_VIEWS and not names["sim"] & STATION_VIEWS
    common = {n for n in names["sim"] if " joints" not in n}
    assert common <= names["hil"]
    rows = logged_rows(recordings["eval"])
    assert rows["/episodes"] == 2 and rows["/world/object/mesh"] == 2  # apple, then mug


@pytest.mark.parametrize("mode", ["hil", "real"])
def test_station_recordings_have_loop_rates_latencies_and_faults(recordings, mode):
    rows = logged_rows(recordings[mode])
    assert rows["/loop/policy/rate_hz"] == 3 and rows["/latency/policy/p99_ms"] > 0
    assert rows["/faults/policy/non_finite"] == rows["/faults/policy/clipped"] == 3 and rows["/faults/log"] >= 1
    if mode == "hil":  # the devices' loops, the world's lag and its object
        for entity in ("/loop/can/rate_hz", "/loop/z1/rate_hz", "/latency/world/lag_ms", "/faults/can/frame_errors",
                       "/world/object_true"):
            assert rows[entity] == 3, entity
    else:
        assert rows["/faults/log"] == 2 and "/world/object_true" not in rows  # start, then the fault


def test_a_station_episode_records_each_control_step_and_the_fault_that_ends_it(tmp_path):
    """run_station_episode hands its logger every control step it completes, then the fault."""
    from dexdrake.systems.diagram import run_station_episode
    from dexdrake.systems.rerun_logger import RerunLogger
    from dexdrake.systems.scenario import load_scenario
    from dexdrake.systems.station import make_station

    scenario = load_scenario(CONFIGS / "hil.yaml")
    scenario.drivers.camera.kind = "sim"
    rrd = tmp_path / "fault.rrd"
    logger = RerunLogger(rrd, "hil", scenario=scenario)
    with make_station(scenario) as station:
        logger.attach(station)
        n, calls = station.hand.num_actuators, []

        def controller(t, hand_state, object_pose):  # the hand's replies stop 5 steps in
            calls.append(t)
            if len(calls) == 5:
                station.devices["allegro_emulator"].stall(2.0)
            return hand_state[:n]

        result = run_station_episode(station, controller, 100, logger)
    logger.close()
    assert result.fault is not None and 0 < result.steps < 100
    rows = logged_rows(rrd)
    assert rows["/loop/policy/rate_hz"] == rows["/task/lift"] == result.steps
    assert ("CRITICAL", result.fault) == text_logs(rrd, "/faults/log")[-1]
