"""The wall-clock emulated world (systems/emulated_world.py, configs/real_emulated_world.yaml):
its process runs the grasp scene's plant in real time with both emulators in it, the real
mode's drivers in their own processes read the plant's joints over udp_multicast CAN and
UDP and move it, and `dexdrake real` runs a supervised episode on it scored on the world's
object. The end-to-end run (1-3 min on a loaded 2-core host, most of it the first global
registration) is `slow`."""

import functools
import multiprocessing
import re
import time

import numpy as np
import pytest

from dexdrake.hands.description import load_hand
from dexdrake.hardware.driver_process import DriverProcess, ProcessConfig, allegro_on_bus, z1_client
from dexdrake.systems.emulated_devices import Emulators
from dexdrake.systems.emulated_world import running_world
from dexdrake.systems.scenario import driver_configs, load_scenario
from dexdrake.systems.scene import ObjectPlacement
from dexdrake.systems.station import can_bus_args

from waiting import wait_for


def _real_time_factor(world, wall_s: float) -> float:
    """The world's simulated time over `wall_s` of wall time, divided by it."""
    t0, w0 = world.time, time.monotonic()
    time.sleep(wall_s)
    return (world.time - t0) / (time.monotonic() - w0)


def test_the_world_process_runs_the_plant_in_real_time_and_the_drivers_read_and_move_its_joints():
    from dexdrake.objects.library import get_object

    scenario = load_scenario("real_emulated_world")
    hand = load_hand(scenario.hand)
    start = hand.pregrasp_vector()  # the world's robot rests here (the separate emulators start at 0)
    placed = ObjectPlacement.from_seed(scenario.seed).pose(get_object(scenario.object))
    emulators = Emulators()
    with running_world(scenario, emulators) as running:
        world = emulators.world
        assert np.allclose(world.object_pose().translation(), placed.translation(), atol=1e-3)
        hand_cfg, arm_cfg = driver_configs(running)
        proc = ProcessConfig(realtime_priority=running.drivers.hand.realtime_priority or 0,
                             heartbeat_timeout_s=5.0)
        with DriverProcess(functools.partial(allegro_on_bus, can_bus_args(running), 0, hand_cfg), proc,
                           "Allegro hand") as fingers, \
                DriverProcess(functools.partial(z1_client, arm_cfg), proc, "Z1 arm") as arm:
            n_arm = len(hand.arm_joints)
            assert np.allclose(arm.state().q, start[:n_arm], atol=0.02)
            assert np.allclose(fingers.state().q, start[hand.hardware_permutation()], atol=0.02)
            time.sleep(1.0)  # the plant moves (the drivers hold the robot); start-up transients pass
            rtf = _real_time_factor(world, 3.0)
            print(f"real-time factor over 3 s: {rtf:.3f}")  # shown with -s
            assert 0.8 <= rtf <= 1.05, rtf  # real time, never ahead of the wall clock
            target = start[:n_arm] + np.array([0.3, 0.0, 0.0, 0.0, 0.0, 0.0])  # the base turns
            arm.command_positions(target)
            assert wait_for(lambda: np.allclose(arm.state().q, target, atol=0.03), 20.0), arm.state().q
            assert arm.state().fault is None and fingers.state().fault is None
            stats = world.stats()
            assert stats["steps"] > 0 and stats["sim_time_s"] > 4.0
    final = emulators.final
    assert final["hand"]["servo_on"] is False and final["arm"]["fsm"] == "PASSIVE"  # the drivers' safe stop
    assert wait_for(lambda: not multiprocessing.active_children(), 10.0)


@pytest.mark.slow
def test_real_emulated_world_runs_a_supervised_episode_scored_on_the_worlds_object(capsys):
    from dexdrake.cli import main

    code = main(["real", "--config", "real_emulated_world", "--yes"])
    out, err = capsys.readouterr()
    assert code == 0, out + err
    for line in ("emulators started in the world process", "dry run: all devices answered", "plan: object can_soda",
                 "episode: 150 control steps", "retreat: the hand opens", "real: finished",
                 "emulated devices after it: hand servo off, max |PWM| 0; arm PASSIVE"):
        assert line in out, out
    scored = re.search(r"episode on the emulated world's object: success=(True|False) max_lift=(-?[\d.]+) m", out)
    world = re.search(r"world: [\d.]+ s simulated in [\d.]+ s wall \(real-time factor ([\d.]+)\)", out)
    assert scored and world, out
    print(f"success={scored[1]} max_lift={scored[2]} m, real-time factor {world[1]}")  # shown with -s
    assert float(world[1]) >= 0.8
    assert wait_for(lambda: not multiprocessing.active_children(), 10.0)
