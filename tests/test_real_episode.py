"""The supervised real episode (`dexdrake real`, systems/real_episode.py) against the
emulator processes of configs/real_emulated.yaml (real transports, the wall clock): it
runs end to end; Ctrl-C, a device fault, a stale pose and a set-point outside the workspace
box each end in the safe stop (hand servo off, arm PASSIVE) with no process left; without
--yes and without a terminal it is refused before anything starts. The workspace box and
the fresh-first-pose rule are also tested on their own. The end-to-end run (20-45 s on a
loaded 2-core host) runs by default; the fault cases are `slow`."""

import concurrent.futures as cf
import multiprocessing
import os
import signal
import threading
import time

import numpy as np
import pytest

from dexdrake.systems.scenario import load_scenario

from waiting import wait_for


def _no_children_left() -> bool:
    return wait_for(lambda: not multiprocessing.active_children(), 10.0)


def _main(args: list[str]) -> int:
    from dexdrake.cli import main

    return main(["real", "--config", *args])


def _mid_episode(monkeypatch, action, delay_s: float = 0.5) -> None:
    """Run `action()` in a thread `delay_s` after the episode's first fresh object pose
    (the end of its held start)."""
    from dexdrake.systems import real_episode

    original = real_episode.run_station_episode

    def run(station, *args, **kwargs):
        def later():
            if wait_for(lambda: station.perception.fresh, 120.0):
                time.sleep(delay_s)
                action()

        threading.Thread(target=later, daemon=True).start()
        return original(station, *args, **kwargs)

    monkeypatch.setattr(real_episode, "run_station_episode", run)


def test_real_without_yes_and_without_a_terminal_is_refused_before_anything_starts(capsys):
    assert _main(["real_emulated"]) == 2
    out, err = capsys.readouterr()
    assert out == "" and err.count("\n") == 1
    assert err.startswith("dexdrake real: error: a real episode moves the robot") and "--yes" in err
    assert not multiprocessing.active_children()


def test_the_workspace_box_refuses_set_points_whose_hand_leaves_it():
    from pydrake.systems.framework import DiagramBuilder
    from pydrake.systems.primitives import ConstantVectorSource

    from dexdrake.hands.description import load_hand
    from dexdrake.errors import StationFault
    from dexdrake.systems.workspace import WorkspaceBox, WorkspaceGuard

    hand = load_hand("allegro_z1")
    box = WorkspaceBox(hand, [-0.45, -0.35, 0.0], [0.45, 0.35, 0.6])
    start = hand.pregrasp_vector()
    assert box.violation(start) is None
    assert np.allclose(box.positions(start)["palm"], [0.0, 0.0, 0.2], atol=1e-3)
    down = start.copy()
    down[1] += 0.6  # the shoulder forward: the hand goes down through the table top
    why = box.violation(down)
    assert why is not None and why.startswith("workspace: the set-point puts the") and "outside the box" in why
    assert box.violation(np.full_like(start, np.nan)) is None  # the command guard's, never sent

    for q, faults in ((start, False), (down, True)):
        builder = DiagramBuilder()
        source = builder.AddSystem(ConstantVectorSource(q))
        guard = builder.AddSystem(WorkspaceGuard(box, len(q), StationFault))
        builder.Connect(source.get_output_port(), guard.get_input_port())
        diagram = builder.Build()
        context = diagram.CreateDefaultContext()
        port = guard.get_output_port()
        if faults:
            with pytest.raises(StationFault, match="^workspace: "):
                port.Eval(guard.GetMyContextFromRoot(context))
        else:
            assert np.array_equal(port.Eval(guard.GetMyContextFromRoot(context)), q)


def test_the_opening_hand_ends_where_a_blocked_finger_stops_and_any_other_move_faults_short_of_its_goal():
    """A retreat's opening hand whose finger the object blocks ends once the joints stand still
    (the arm then lifts it clear); a move without `settle_s` still faults short of its goal."""
    from types import SimpleNamespace

    from dexdrake.errors import StationFault
    from dexdrake.systems.real_episode import move_to

    class Station:  # joints follow their set-points at once, the last one stops at 0.3 rad
        scenario = SimpleNamespace(control_period=0.005,
                                   real=SimpleNamespace(move_speed=20.0, move_tolerance=0.05, move_timeout_s=0.5))

        def __init__(self):
            self.q = np.zeros(3)

        def send(self, q):
            self.q = np.minimum(q, [np.inf, np.inf, 0.3])

        def positions(self):
            return self.q.copy()

    station = Station()
    assert move_to(station, np.full(3, 1.0), "open", settle_s=0.1) < 0.4
    assert np.allclose(station.q, [1.0, 1.0, 0.3])
    assert move_to(station, np.array([0.5, 0.5, 0.0]), "open", settle_s=0.1) < 0.2  # at the goal: no settling
    with pytest.raises(StationFault, match=r"^arm: still 0\.700 rad from the goal 0 s after its last set-point"):
        move_to(Station(), np.full(3, 1.0), "arm")


def test_a_first_pose_older_than_the_age_limit_waits_for_a_fresh_one():
    """A global registration slower than max_pose_age_s (a Kinect's ~3 s against 2 s) is not
    a stale pose: the station waits for the tracking after it; once a fresh pose came, an
    old one is a fault as before."""
    from dexdrake.systems.scenario import CameraDriver
    from dexdrake.errors import StationFault
    from dexdrake.systems.station import PerceptionSystem

    hang = threading.Event()
    calls = []

    def estimate(color, depth, intrinsics, X_WC, prior=None, track=False):
        calls.append(track)
        if not track:
            time.sleep(0.5)  # the global registration: older than the limit when it arrives
        elif len(calls) > 3:
            hang.wait(5.0)  # then the worker hangs
        return {"success": True, "reason": "", "X_WO": np.eye(4), "fitness": 1.0, "method": "global" if not track
                else "track", "cpu_s": 0.0}

    class Frame:
        color = np.zeros((2, 2, 3), np.uint8)
        depth = np.zeros((2, 2), np.uint16)
        X_WC = None

        class intrinsics:
            width = height = 2
            fx = fy = cx = cy = 1.0

    camera = CameraDriver(kind="rendered", period_s=0.05, max_pose_age_s=0.3, first_pose_timeout_s=10.0)
    system = PerceptionSystem(Frame, cf.ThreadPoolExecutor(1), camera, estimate)
    try:
        system.wait_for_first_pose()
        assert system.fresh and calls[0] is False and True in calls
        with pytest.raises(StationFault, match=r"object pose 0\.3\d s old \(limit 0\.3 s\)"):
            t0 = time.monotonic()
            while time.monotonic() - t0 < 3.0:
                system.poll()
                time.sleep(0.01)
    finally:
        hang.set()


def _last_line(err: str) -> str:
    """The command's own last line (the policy's warning from the dry run comes before it)."""
    lines = err.splitlines()
    assert lines and all(line.startswith("warning: ") for line in lines[:-1]), err
    return lines[-1]


def _safely_stopped(out: str) -> None:
    assert "safe stop: hand zero torque, then servo off; arm held, then PASSIVE" in out, out


def test_real_emulated_runs_a_supervised_episode_end_to_end(tmp_path, capsys):
    rrd = tmp_path / "real.rrd"
    code = _main(["real_emulated", "--yes", "--rrd", str(rrd)])
    out, err = capsys.readouterr()
    assert code == 0, out + err
    for line in ("emulators started in their own processes", "dry run: all devices answered", "plan: object box_cube",
                 "confirmed by --yes", "move to the start pose", "arrived in", "episode: 100 control steps",
                 "retreat: the hand opens", "done in", "emulated devices after it: hand servo off, max |PWM| 0; arm PASSIVE",
                 "real: finished"):
        assert line in out, out
    _safely_stopped(out)
    assert rrd.stat().st_size > 0
    assert _no_children_left()


@pytest.mark.slow
def test_ctrl_c_during_the_episode_ends_in_the_safe_stop(capsys, monkeypatch):
    """Two SIGINTs 1 ms apart during the episode: exit 130, the hand's servo off, the arm
    PASSIVE, no process left."""
    def interrupt():
        os.kill(os.getpid(), signal.SIGINT)
        time.sleep(0.001)
        os.kill(os.getpid(), signal.SIGINT)

    _mid_episode(monkeypatch, interrupt)
    code = _main(["real_emulated", "--yes", "--horizon", "500"])
    out, err = capsys.readouterr()
    assert code == 130, out + err
    assert _last_line(err) == "dexdrake real: interrupted: the devices were stopped safely", err
    _safely_stopped(out)
    assert "emulated devices after it: hand servo off, max |PWM| 0; arm PASSIVE" in out
    assert _no_children_left()


@pytest.mark.slow
def test_a_device_fault_mid_episode_ends_in_a_fault_stop(capsys, monkeypatch):
    """The hand's emulator dies during the episode (a dead CAN bus): exit 1, one line naming
    the hand's fault; the arm left PASSIVE; no process left."""
    def kill_the_hand():
        (proc,) = [p for p in multiprocessing.active_children() if p.name == "dexdrake-allegro-emulator"]
        os.kill(proc.pid, signal.SIGKILL)

    _mid_episode(monkeypatch, kill_the_hand)
    code = _main(["real_emulated", "--yes", "--horizon", "500"])
    out, err = capsys.readouterr()
    assert code == 1, out + err
    assert _last_line(err).startswith("dexdrake real: fault stop in episode: Allegro hand"), err
    _safely_stopped(out)
    assert "emulated devices after it: hand not reported; arm PASSIVE" in out
    assert _no_children_left()


@pytest.mark.slow
def test_a_stale_pose_mid_episode_ends_in_a_fault_stop(capsys, monkeypatch):
    """Perception's worker stops answering during the episode: once the last pose is older
    than max_pose_age_s the station stops (exit 1, one line naming the pose's age)."""
    from dexdrake.systems import station

    hang = threading.Event()
    original = station.perception_executor

    class Hanging(cf.Executor):
        def __init__(self, inner):
            self.inner = inner

        def submit(self, fn, *args, **kwargs):
            return cf.Future() if hang.is_set() else self.inner.submit(fn, *args, **kwargs)

        def shutdown(self, wait=True, *, cancel_futures=False):
            self.inner.shutdown(wait=wait, cancel_futures=cancel_futures)

    monkeypatch.setattr(station, "perception_executor", lambda mesh: Hanging(original(mesh)))
    _mid_episode(monkeypatch, hang.set)
    code = _main(["real_emulated", "--yes", "--horizon", "1000"])
    out, err = capsys.readouterr()
    assert code == 1, out + err
    assert _last_line(err).startswith("dexdrake real: fault stop in episode: object pose") and \
        _last_line(err).endswith("s old (limit 5.0 s)"), err
    _safely_stopped(out)
    assert "emulated devices after it: hand servo off, max |PWM| 0; arm PASSIVE" in out
    assert _no_children_left()


@pytest.mark.slow
def test_a_move_whose_set_point_leaves_the_workspace_box_is_a_fault_stop(tmp_path, capsys):
    """The emulated arm rests with its hand hanging below the table top: with a box whose
    floor is the table top the move's first set-point (the measured pose) leaves it: exit 1
    before anything moved, hand servo off, arm PASSIVE."""
    from dexdrake.systems.scenario import scenario_path

    text = scenario_path("real_emulated").read_text().replace("workspace_lower: [-0.7, -0.35, -0.3]",
                                                               "workspace_lower: [-0.7, -0.35, 0.0]")
    assert "workspace_lower: [-0.7, -0.35, 0.0]" in text
    config = tmp_path / "boxed.yaml"
    config.write_text(text)
    assert load_scenario(config).real.workspace_lower == [-0.7, -0.35, 0.0]
    code = _main([str(config), "--yes"])
    out, err = capsys.readouterr()
    assert code == 1, out + err
    assert _last_line(err).startswith("dexdrake real: fault stop in move to the start pose: workspace: the "
                                      "set-point puts the"), err
    assert "arrived in" not in out
    _safely_stopped(out)
    assert "emulated devices after it: hand servo off, max |PWM| 0; arm PASSIVE" in out
    assert _no_children_left()
