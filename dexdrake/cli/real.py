"""Sub-command `real`: the real Allegro + Z1 + Kinect station. `--dry-run`: connectivity
checks, the plan and the mode's whole diagram, built around drivers that are never started;
moves nothing. Without it: the dry run's checks, the plan, the operator's confirmation,
then a supervised episode (systems/real_episode.py) ending in the safe stop; exit 0
finished, 1 fault stop, 130 interrupted."""

from __future__ import annotations

import argparse
import contextlib
import sys

import numpy as np

from dexdrake import argtypes
from dexdrake.cli.flags import MISMATCH_HELP, add_horizon
from dexdrake.cli.hil import format_rate, format_world
from dexdrake.errors import DexdrakeError


def add_parser(subparsers) -> None:
    real = subparsers.add_parser("real", help="the real Allegro + Z1 + Kinect station")
    real.add_argument("--config", required=True, help="scenario (mode real): a packaged name (real) or a YAML path")
    real.add_argument("--dry-run", action="store_true",
                      help="check connectivity, print limits, the plan and the diagram; move nothing")
    real.add_argument("--yes", action="store_true",
                      help="start the episode without asking (scripted use); else Enter on a terminal confirms")
    add_horizon(real, None, "default: the scenario's real.horizon")
    real.add_argument("--rrd", type=argtypes.output_file(".rrd"), help="write a rerun recording of the episode to this .rrd file")
    real.add_argument("--allow-scenario-mismatch", action="store_true", help=MISMATCH_HELP)
    real.set_defaults(func=run_real)


def run_real(args: argparse.Namespace) -> int:
    from dexdrake.systems.emulated_devices import Emulators
    from dexdrake.systems.emulated_world import running_devices
    from dexdrake.systems.scenario import EMULATED_PROCESS_KINDS
    from dexdrake.systems.scenario import ScenarioError, load_scenario

    scenario = load_scenario(args.config)
    if scenario.mode != "real":
        raise ScenarioError(f"{args.config} is a {scenario.mode} scenario; `real` needs hardware drivers")
    if not (args.dry_run or args.yes or (sys.stdin is not None and sys.stdin.isatty())):
        raise DexdrakeError("a real episode moves the robot and waits for the operator's Enter: run it "
                            "from a terminal, or pass --yes for scripted use")
    emulators = Emulators() if scenario.drivers.hand.kind in EMULATED_PROCESS_KINDS else None
    outcome = None
    try:
        with contextlib.ExitStack() as stack:
            if emulators is not None:
                scenario = stack.enter_context(running_devices(scenario, emulators))
                where = "in the world process" if emulators.world is not None else "in their own processes"
                print(f"emulators started {where} (pids {emulators.pids}): Allegro on "
                      f"{scenario.drivers.hand.interface}:{scenario.drivers.hand.channel} port "
                      f"{scenario.drivers.hand.port}, Z1 on UDP {scenario.drivers.arm.controller_port} -> "
                      f"{scenario.drivers.arm.local_port}")
            code = dry_run(scenario, args.allow_scenario_mismatch)
            if args.dry_run or code != 0:
                return code
            outcome = _supervised(scenario, args, emulators.world if emulators is not None else None)
    except KeyboardInterrupt:
        _report_stop(emulators)
        print("dexdrake real: interrupted: the devices were stopped safely", file=sys.stderr)
        return 130
    _report_stop(emulators)
    if outcome.fault is not None:
        print(f"dexdrake real: fault stop in {outcome.phase}: {outcome.fault}", file=sys.stderr)
        return 1
    print("real: finished; the devices were stopped safely")
    return 0


def _report_stop(emulators) -> None:
    """What the safe stop did, and for emulated devices the state they were left in."""
    print("safe stop: hand zero torque, then servo off; arm held, then PASSIVE")
    if emulators is not None and emulators.processes:
        final = emulators.final
        hand, arm = final.get("hand"), final.get("arm")
        print("  emulated devices after it: hand " + ("not reported" if hand is None else
              f"servo {'ON' if hand['servo_on'] else 'off'}, max |PWM| {hand['max_abs_pwm']:.0f}")
              + "; arm " + ("not reported" if arm is None else arm["fsm"]))


def _confirm(yes: bool) -> None:
    """The operator's Enter (or --yes); DexdrakeError when stdin gives none."""
    if yes:
        print("confirmed by --yes")
        return
    try:
        input("press Enter to start (Ctrl-C aborts): ")
    except EOFError:
        raise DexdrakeError("no confirmation (stdin closed); nothing was moved") from None


def _supervised(scenario, args: argparse.Namespace, world=None):
    """The plan, the confirmation, and the supervised episode in the station's context (its
    exit is the safe stop, whatever happens inside); `world`: an emulated world's WorldView."""
    from dexdrake.hands.description import load_hand
    from dexdrake.systems.controllers import make_controller
    from dexdrake.systems.real_episode import run_supervised
    from dexdrake.systems.station import make_station
    from dexdrake.systems.workspace import WorkspaceBox

    real, hand = scenario.real, load_hand(scenario.hand)
    steps = args.horizon or real.horizon
    rrd = args.rrd or scenario.rrd
    # the dry run has printed this policy's warnings already
    controller, description = make_controller(scenario, args.allow_scenario_mismatch, warn=lambda line: None)
    start = hand.pregrasp_vector()
    box = WorkspaceBox(hand, real.workspace_lower, real.workspace_upper)
    n_arm = len(hand.arm_joints)
    print(f"plan: object {scenario.object} (seed {scenario.seed}), controller {description}")
    print(f"  start pose: arm {np.round(start[:n_arm], 3).tolist()} rad, hand open (pre-grasp); palm centre at "
          f"{np.round(box.positions(start)['palm'], 3).tolist()} m")
    print(f"  workspace box {real.workspace_lower} .. {real.workspace_upper} m (palm centre and fingertips; "
          "a set-point outside it is a fault stop)")
    print(f"  moves: the Z1 arm ({n_arm} joints) and the Allegro hand ({hand.num_actuators - n_arm} joints): to the "
          f"start pose at {real.move_speed} rad/s, {steps} control steps ({steps * scenario.control_period:.1f} s), "
          "then retreat (hand opens, arm back to the start pose), then the safe stop")
    why = box.violation(start)
    if why is not None:
        raise DexdrakeError(f"the start pose leaves the workspace box: {why}")
    _confirm(args.yes)
    logger = None
    if rrd:
        from dexdrake.systems.rerun_logger import RerunLogger

        logger = RerunLogger(rrd, scenario.mode, scenario=scenario)
    try:
        with make_station(scenario, world=world) as station:
            if logger is not None:
                logger.attach(station)
            outcome = run_supervised(station, controller, steps, logger)
    finally:
        if logger is not None:
            logger.close()
    if outcome.episode is not None:
        stats = outcome.episode.stats
        for key, name in (("can", "CAN (Allegro PD loop)"), ("z1", "Z1 UDP loop"), ("policy", "policy/control")):
            if key in stats:
                print("  " + format_rate(name, stats[key]))
        if "world" in stats:  # an emulated world: the object's true pose scores the episode
            print("  " + format_world(stats["world"]))
            print(f"  episode on the emulated world's object: success={outcome.episode.success} "
                  f"max_lift={outcome.episode.max_lift:.3f} m")
    if rrd:
        print(f"  recording: {rrd}")
    return outcome


def dry_run(scenario, allow_scenario_mismatch: bool = False) -> int:
    """Connectivity checks; prints limits, the plan and the diagram (built, never run);
    commands nothing."""
    from dexdrake.hands.description import load_hand
    from dexdrake.hardware.allegro_can import AllegroHand, check_allegro_config
    from dexdrake.hardware.safety import HardwareError
    from dexdrake.hardware.z1_model import NUM_ARM_JOINTS, z1_model
    from dexdrake.hardware.z1_udp import Z1Arm, check_z1_config
    from dexdrake.systems.controllers import make_controller
    from dexdrake.systems.diagram import scenario_diagram
    from dexdrake.systems.scenario import driver_configs
    from dexdrake.systems.station import make_station, open_can_bus

    hand = load_hand(scenario.hand)
    h, c = scenario.drivers.hand, scenario.drivers.camera
    hand_cfg, arm_cfg = driver_configs(scenario)
    hs, zs = check_allegro_config(hand_cfg), check_z1_config(arm_cfg)
    print(f"real dry run: {scenario.name} hand={scenario.hand} object={scenario.object}")
    lower = np.concatenate([zs.target_lower, hs.target_lower])  # targets: the margin inside the limits
    upper = np.concatenate([zs.target_upper, hs.target_upper])
    joints = list(hand.arm_joints) + list(hand.hardware_joints)
    print(f"  target ranges: the joint limits less {arm_cfg.limit_margin_rad} rad (arm), "
          f"{hand_cfg.limit_margin_rad} rad (hand)")
    for j, l, u in zip(joints, lower, upper):
        print(f"  limit {j:<11} [{l:+.3f}, {u:+.3f}] rad")
    print(f"  hand: max target rate {hand_cfg.max_target_rate} rad/s, watchdog "
          f"{hand_cfg.watchdog_timeout_s * 1e3:.0f} ms, PWM limits {hs.pwm_limit.astype(int).tolist()}")
    print(f"  arm: {arm_cfg.mode.name}, max velocity {zs.max_velocity:.3f} rad/s, watchdog "
          f"{arm_cfg.watchdog_timeout_s * 1e3:.0f} ms, effort {zs.effort.tolist()} N*m, gravity "
          f"feed-forward {'on' if arm_cfg.gravity_feedforward else 'off'}; payload "
          f"{z1_model().payload_kg:.3f} kg (the hand, from the model): set it as `load` in "
          "z1_controller/config/config.xml")
    # a policy that cannot run is refused here
    controller, description = make_controller(scenario, allow_scenario_mismatch)
    print(f"  controller: {description}; control period {scenario.control_period * 1e3:.0f} ms")
    print(f"  perception ({c.kind}): a frame every {c.period_s * 1e3:.0f} ms, "
          + ("tracked from the last pose (global registration for the first pose and when tracking is lost)"
             if c.tracking else "each registered globally")
          + f", the pose moved on to the present by at most {c.predict_s * 1e3:.0f} ms; "
          f"{c.max_consecutive_failures} failures in a row: {c.on_failure}")
    ok = True
    # the mode's whole diagram, around drivers that are made but never started (nothing is sent)
    try:
        with make_station(scenario, start=False) as station:
            print(f"  diagram (built, not run): {scenario_diagram(station, controller).describe()}")
    except HardwareError as err:
        ok = False
        print(f"  diagram: FAILED: {err}")
    # CAN: the driver's probe (RTR info and serial requests only: nothing moves)
    try:
        bus = open_can_bus(scenario)
        try:
            info = AllegroHand(bus, h.device_id, hand_cfg).probe()
            print(f"  CAN {h.interface}:{h.channel}: OK, {info}")
        finally:
            bus.shutdown()
    except HardwareError as err:
        ok = False
        print(f"  CAN {h.interface}:{h.channel}: FAILED: {err}")
    # Z1: the driver's probe sends nothing (the protocol has no pure query)
    a = arm_cfg
    where = f"Z1 {a.host}:{a.local_port} -> {a.controller_port}"
    try:
        found = Z1Arm(a).probe()
        heard = ("" if found.state is None else f", state {found.state.state.name} heard, q = "
                 f"{np.round([j.Pos for j in found.state.joints[:NUM_ARM_JOINTS]], 3).tolist()}")
        if found.controller_bound is False:
            ok = False
            print(f"  {where}: FAILED: nothing is bound to port {a.controller_port} (is z1_controller running?)")
        else:
            bound = {True: "controller port bound", None: "controller port not checked (remote host)"}
            print(f"  {where}: OK, client port free, {bound[found.controller_bound]}{heard}; "
                  "nothing sent (the protocol has no pure query)")
    except HardwareError as err:
        ok = False
        print(f"  {where}: FAILED: {err}")
    # camera: one frame, read as the station reads it
    try:
        from dexdrake.systems.station import camera_reader

        with contextlib.ExitStack() as camera:
            frame = camera_reader(scenario, None, camera)()
            print(f"  camera {c.kind}: OK, frame {frame.color.shape[1]}x{frame.color.shape[0]}")
    except DexdrakeError as err:
        ok = False
        print(f"  camera {c.kind}: FAILED: {err}")
    if not ok:
        print("dry run: hardware not ready (nothing was moved)")
        return 1
    print("dry run: all devices answered (nothing was moved)")
    return 0
