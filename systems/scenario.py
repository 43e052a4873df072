"""Typed station scenarios: one YAML file says what the station is built from.

Modelled on Drake's `manipulation` station: a dataclass tree loaded with
`pydrake.common.yaml.yaml_load_typed`, with one driver entry per device saying whether it
is simulated, emulated (hardware-in-the-loop: the real driver code against a device
emulator whose joint dynamics come from a Drake plant) or real hardware.

    scenario = load_scenario("hil")  # the packaged configs/hil.yaml; a path is a path
    scenario.mode  # "sim" | "hil" | "real"

Every mode steps its plant (the sim station, the HIL world, training's GraspEnv) at the
scenario's `time_step` (5 ms by default) and runs its controller every `control_period`
(20 ms). `scenario_record` is the part a policy's behaviour depends on (step, period, the
drivers' target limits, the perception model, noise); training stores it in the checkpoint and
`check_policy_scenario` compares it with the scenario a policy is run under (both in
systems/scenario_record.py).

Modes follow from the driver kinds:
  sim   hand and arm kind "sim" (the Drake grasp scene; camera "sim" = ground-truth pose)
  hil   hand and arm "emulated"; camera "sim" (pose from the co-simulated world) or
        "rendered" (Drake-rendered RGB-D of the world -> segmentation -> registration)
  real  hand and arm "hardware"; camera "k4a" (Azure Kinect) or "recorded" (replay); or
        hand and arm "emulated_process": the real mode's code path against emulators that
        `dexdrake real` starts in processes of their own (systems/emulated_devices.py), on
        real transports and the wall clock, with camera "recorded" or "rendered" (a static
        scene: the object where the seed places it, rendered; nothing moves it); or hand and
        arm "emulated_world": the same against one process running the grasp scene's plant in
        real time with both emulators in it (systems/emulated_world.py), camera "rendered"
        (the object where the world has it now)
"""

import dataclasses as dc
import math
import typing
from importlib.resources import files
from pathlib import Path
from typing import Optional

import yaml
from pydrake.common.yaml import yaml_load_typed

from dexdrake.errors import DexdrakeError
from dexdrake.perceived_pose import PerceptionModel
from dexdrake.hands.allegro_units import NUM_JOINTS as NUM_HAND_JOINTS
from dexdrake.hands.allegro_units import NM_PER_PWM
from dexdrake.hardware.z1_model import NUM_ARM_JOINTS

HAND_KINDS = ("sim", "emulated", "emulated_process", "emulated_world", "hardware")
EMULATED_PROCESS_KINDS = ("emulated_process", "emulated_world")  # real mode, devices in processes
CAMERA_KINDS = ("sim", "rendered", "recorded", "k4a")
CONTACT_APPROXIMATIONS = ("sap", "similar", "lagged")  # Drake's discrete contact approximations on the SAP solver
ARM_MODES = ("LOWCMD", "JOINTCTRL")
PERCEPTION_FAILURE_POLICIES = ("hold", "stop")


class ScenarioError(DexdrakeError):
    """A scenario file that cannot be loaded or does not make a valid station."""


@dc.dataclass
class HandDriver:
    """The Allegro hand. Gains and limits are 16 values in CAN bus order. None means the
    driver's default (hardware/allegro_can.AllegroConfig: the vendor gains and PWM limits,
    the model's joint limits); values beyond those limits are refused at load."""

    kind: str = "sim"
    interface: str = "virtual"  # python-can interface: virtual | socketcan | pcan | ...
    channel: str = "dexdrake_allegro"  # socketcan: "can0"; udp_multicast: the group address
    # udp_multicast: the UDP port (None: python-can's default; 0, emulated_process/world only: a free one)
    port: Optional[int] = None
    bitrate: int = 1_000_000
    device_id: int = 0
    kp: Optional[list[float]] = None  # PWM per rad
    kd: Optional[list[float]] = None  # PWM per rad/s
    pwm_limit: Optional[list[float]] = None
    lower: Optional[list[float]] = None  # rad
    upper: Optional[list[float]] = None
    max_target_rate: Optional[float] = None  # rad/s
    limit_margin_rad: Optional[float] = None  # targets stay this far inside the joint limits
    watchdog_timeout_s: Optional[float] = None
    status_timeout_s: Optional[float] = None  # no status reply for this long (s): fault
    temperature_timeout_s: Optional[float] = None  # no temperature of a finger for this long (s): fault
    # run the driver loop in its own process (hardware/driver_process.py); None: hardware
    # and emulated_process yes, emulated no (the simulated-clock HIL steps its drivers in
    # lockstep in-process)
    process: Optional[bool] = None
    # with `process`: that process's threads run SCHED_FIFO at this priority (1..99; needs
    # CAP_SYS_NICE or `ulimit -r`, refused at start otherwise), so that the host's load
    # cannot delay them; None: normal scheduling
    realtime_priority: Optional[int] = None
    # with `process`: that process safe-stops the device when the parent's heartbeat is this
    # old (s: a hung, starved or dead parent); None: the default of
    # hardware/driver_process.ProcessConfig
    heartbeat_timeout_s: Optional[float] = None


@dc.dataclass
class ArmDriver:
    """The Unitree Z1 (UDP). Port 0 means a free ephemeral port (emulated only). None means
    the driver's default (hardware/z1_udp.Z1Config: ports 8072 -> 8071, the model's LOWCMD
    gains and joint limits, 2 rad/s on targets); values beyond the model's limits are refused at load."""

    kind: str = "sim"
    host: str = "127.0.0.1"
    local_port: Optional[int] = None
    controller_port: Optional[int] = None
    mode: str = "LOWCMD"
    kp: Optional[list[float]] = None  # raw LOWCMD gains
    kd: Optional[list[float]] = None
    max_velocity: Optional[float] = None  # rad/s on targets
    limit_margin_rad: Optional[float] = None  # targets stay this far inside the joint limits
    velocity_feedforward: Optional[bool] = None  # send the reference's velocity (W) with it
    watchdog_timeout_s: Optional[float] = None
    process: Optional[bool] = None  # as HandDriver.process
    realtime_priority: Optional[int] = None  # as HandDriver.realtime_priority
    heartbeat_timeout_s: Optional[float] = None  # as HandDriver.heartbeat_timeout_s


@dc.dataclass
class CameraDriver:
    """The RGB-D camera and the perception that turns it into an object pose."""

    kind: str = "sim"
    width: int = 320
    height: int = 180
    intrinsics: Optional[list[float]] = None  # fx, fy, cx, cy; None: Kinect colour, scaled
    eye: list[float] = dc.field(default_factory=lambda: [0.5, 0.0, 0.45])  # camera position (m)
    target: list[float] = dc.field(default_factory=lambda: [0.0, 0.0, 0.03])  # looked-at point
    recording: str = ""  # kind "recorded": a folder of frame_*.npz or one .npz
    device_id: int = 0  # kind "k4a"
    depth_noise: bool = True  # kind "rendered": Kinect-like depth noise
    period_s: float = 0.5  # how often a new pose estimate is started
    # follow the last pose frame to frame (ICP, a few ms) and register globally (about
    # 0.6 s) only for the first pose or when tracking is lost; false: register every frame
    tracking: bool = True
    # the pose used is the last estimate moved on at its track's velocity (from the last two
    # frames) to the present, by at most this (s): the frame's age; 0: the estimate as is
    predict_s: float = 0.1
    first_pose_timeout_s: float = 30.0  # no pose at all by then -> stop
    # the age of the last pose's frame (s), once a pose came: older than hold_pose_age_s the
    # station holds (hand and arm keep the positions measured then; the controller's commands
    # resume with a younger pose); older than max_pose_age_s it stops (safe stop)
    hold_pose_age_s: float = 1.0
    max_pose_age_s: float = 2.0
    max_consecutive_failures: int = 3  # then `on_failure` applies
    on_failure: str = "hold"  # hold: keep the last pose | stop: safe stop the station


@dc.dataclass
class Drivers:
    hand: HandDriver = dc.field(default_factory=HandDriver)
    arm: ArmDriver = dc.field(default_factory=ArmDriver)
    camera: CameraDriver = dc.field(default_factory=CameraDriver)


@dc.dataclass
class HilWorldConfig:
    """How the co-simulated world turns bus commands into plant torques (hil only).
    Its timing (one simulated clock, lockstep with the hand's PD loop, never faster than
    real time) is described in systems/hil_world.py.

    A finger joint gets tau = pwm * pwm_torque_scale * NM_PER_PWM (the one PWM -> N*m
    assumption, dexdrake/hands/allegro_units.py, which the simulated hand's gains use too);
    its reflected motor inertia and damping keep the firmware emulator's PWM model
    (ddq = accel_per_pwm * pwm - damping * dq) at that torque scale."""

    pwm_torque_scale: float = 1.0  # multiplies NM_PER_PWM (a sensitivity knob; 1 = as simulated)
    max_lag_s: float = 0.05  # at most this much lag behind the wall clock is caught up
    reply_timeout_s: float = 0.1  # wall time a world step waits for the hand's torque reply


@dc.dataclass
class RealEpisode:
    """A supervised real episode (`dexdrake real`): the move to the start pose (the hand's
    pre-grasp pose), `horizon` control periods of the controller, the retreat (the hand opens,
    then the arm goes back to the start pose), each move at `move_speed` on its fastest
    joint (and never faster than the drivers' own target rates). Every set-point, the
    moves' and the controller's, keeps the palm centre and the fingertips inside the
    workspace box (world frame, m), else the episode ends in a fault stop
    (systems/workspace.py)."""

    horizon: int = 150  # control steps (`dexdrake real --horizon` overrides it)
    workspace_lower: list[float] = dc.field(default_factory=lambda: [-0.45, -0.35, 0.0])
    workspace_upper: list[float] = dc.field(default_factory=lambda: [0.45, 0.35, 0.6])
    move_speed: float = 0.3  # rad/s, the fastest joint of a move
    move_tolerance: float = 0.05  # rad: a move ends when every joint is this close to its goal
    move_timeout_s: float = 30.0  # a move that has not arrived by then is a fault


@dc.dataclass
class PolicyEntry:
    checkpoint: str = ""  # a dexdrake policy checkpoint (.pt); no `policy` entry: the scripted grasp
    feature_set: str = "DexRep"
    # DexRepSystem's distance queries (dexdrake/dexrep/feature_sets.FeaturePath): "fast", the
    # object's cached geometry at the object pose (perceived in hil/real), or "scenegraph",
    # SceneGraph's signed distances to the simulated object (sim only)
    feature_path: str = "fast"


@dc.dataclass
class Scenario:
    name: str = "sim"
    hand: str = "allegro_z1"
    object: str = "box_cube"
    seed: int = 0
    time_step: float = 0.005  # plant step (s), every mode
    contact_approximation: str = "sap"  # the plant's discrete contact approximation (CONTACT_APPROXIMATIONS)
    control_period: float = 0.02  # command / policy period (s)
    drivers: Drivers = dc.field(default_factory=Drivers)
    hil: HilWorldConfig = dc.field(default_factory=HilWorldConfig)
    real: RealEpisode = dc.field(default_factory=RealEpisode)
    # how the features see the object pose in sim mode (dexdrake/perceived_pose.py: the paper's
    # pose noise, the perception pipeline's frame period and latency); in hil and real the
    # camera pipeline is the perception and this entry is what its policy was trained under
    perception: PerceptionModel = dc.field(default_factory=PerceptionModel)
    policy: Optional[PolicyEntry] = None
    rrd: Optional[str] = None  # write a rerun recording of the loop here

    @property
    def torque_per_pwm(self) -> float:
        """N*m per PWM count in the HIL world (the assumption times its scale)."""
        return NM_PER_PWM * self.hil.pwm_torque_scale

    @property
    def mode(self) -> str:
        """"sim", "hil" or "real" (see the module docstring); valid after validation."""
        return {"sim": "sim", "emulated": "hil", "emulated_process": "real", "emulated_world": "real",
                "hardware": "real"}[self.drivers.hand.kind]


def packaged_scenarios() -> list[str]:
    """Names of the scenario files shipped in the package (configs/*.yaml: sim, hil, real)."""
    return sorted(p.name.removesuffix(".yaml") for p in files("dexdrake.configs").iterdir()
                  if p.name.endswith(".yaml"))


def scenario_path(name_or_path: str | Path) -> Path:
    """A packaged scenario's file for a bare name (`hil`: configs/hil.yaml inside the
    installed package, from any working directory); anything else is a path as given."""
    text = str(name_or_path)
    if text in packaged_scenarios():
        return Path(str(files("dexdrake.configs").joinpath(f"{text}.yaml")))
    return Path(name_or_path)


def load_scenario(name_or_path: str | Path) -> Scenario:
    """Load and validate a scenario (a packaged name or a YAML path, `scenario_path`);
    ScenarioError says what is wrong."""
    path = scenario_path(name_or_path)
    if path.is_dir():
        raise ScenarioError(f"scenario file {path} is a folder; give a .yaml file or a packaged name "
                            f"({', '.join(packaged_scenarios())})")
    if not path.is_file():
        raise ScenarioError(f"scenario file {path} does not exist (packaged scenarios: "
                            f"{', '.join(packaged_scenarios())})")
    return parse_scenario(path.read_text(), source=str(name_or_path))


_KINDS = {float: ("a number", (int, float)), int: ("an integer", (int,)), str: ("a string", (str,)),
          bool: ("true or false", (bool,))}


def _check_types(data: object, schema: type, source: str, prefix: str = "") -> None:
    """ScenarioError naming the first field of `data` (parsed YAML) whose value is not of its
    `schema` field's scalar type (number, integer, string, bool), nested entries included."""
    if not isinstance(data, dict):
        raise ScenarioError(f"{source}: {'the file' if not prefix else prefix.rstrip('.')} holds "
                            f"{'nothing' if data is None else repr(data)}, not `field: value` lines "
                            f"(fields: {', '.join(f.name for f in dc.fields(schema))})")
    hints = typing.get_type_hints(schema)
    for key, value in data.items():
        hint = hints.get(key)
        args = [a for a in typing.get_args(hint) if a is not type(None)]
        if typing.get_origin(hint) is typing.Union and len(args) == 1:  # Optional[X]
            if value is None:
                continue
            hint = args[0]
        if dc.is_dataclass(hint) and value is not None:
            _check_types(value, hint, source, f"{prefix}{key}.")
        elif hint in _KINDS and not _reads_as(value, hint):
            raise ScenarioError(f"{source}: field {prefix}{key} must be {_KINDS[hint][0]}, got {value!r}")


RENAMED = {("real", "steps"): "real.horizon"}  # (section, old field) -> the field's name now


def _check_renamed(data: object, source: str) -> None:
    """ScenarioError naming the new name of the first renamed field that `data` (parsed YAML) uses."""
    for (section, old), new in RENAMED.items():
        entry = data.get(section) if isinstance(data, dict) else None
        if isinstance(entry, dict) and old in entry:
            raise ScenarioError(f"{source}: field {section}.{old} is now {new}")


def _reads_as(value: object, kind: type) -> bool:
    """Whether Drake's YAML reader takes `value` (as PyYAML parsed it) for a `kind` field; it
    also reads numbers PyYAML leaves as strings, such as 1.0e9."""
    if isinstance(value, str) and kind in (int, float):
        try:
            kind(value)
        except ValueError:
            return False
        return True
    return isinstance(value, bool) == (kind is bool) and isinstance(value, _KINDS[kind][1])


def parse_scenario(text: str, source: str = "<string>") -> Scenario:
    """Load and validate a scenario from YAML text."""
    try:
        data = yaml.safe_load(text)
    except yaml.YAMLError as err:
        raise ScenarioError(f"{source}: not valid YAML ({' '.join(str(err).split())})") from None
    _check_renamed(data, source)
    _check_types(data, Scenario, source)
    try:
        scenario = yaml_load_typed(schema=Scenario, data=text)
    except Exception as err:  # yaml_load_typed raises RuntimeError/TypeError/yaml errors
        raise ScenarioError(f"{source}: {err}") from None
    validate_scenario(scenario, source)
    return scenario


def _require(ok: bool, source: str, message: str) -> None:
    if not ok:
        raise ScenarioError(f"{source}: {message}")


def _check_vector(values: Optional[list[float]], n: int, name: str, source: str) -> None:
    if values is None:
        return
    _require(len(values) == n and all(math.isfinite(v) for v in values), source,
             f"{name} needs {n} finite values, got {values}")


def is_multiple(period: float, step: float) -> bool:
    """True if `period` is a whole number (>= 1) of `step`s (to 1e-9 relative)."""
    n = round(period / step)
    return n >= 1 and abs(n * step - period) <= 1e-9 * period


def own_process(driver: HandDriver | ArmDriver) -> bool:
    """Whether a hand or arm driver entry runs its driver loop in its own process."""
    if driver.process is None:
        return driver.kind in ("hardware", *EMULATED_PROCESS_KINDS)
    return driver.process


def process_config(driver: HandDriver | ArmDriver):
    """The ProcessConfig (hardware/driver_process.py) of a driver entry run in its own
    process; HardwareError names a value it refuses."""
    from dexdrake.hardware.driver_process import ProcessConfig

    given = {} if driver.heartbeat_timeout_s is None else {"heartbeat_timeout_s": driver.heartbeat_timeout_s}
    return ProcessConfig(realtime_priority=driver.realtime_priority or 0, **given)


def driver_configs(s: Scenario, arm_controller_port: int | None = None,
                   arm_local_port: int | None = None):
    """(AllegroConfig, Z1Config) of a hil/real scenario, checked against the limits (the
    drivers' `check_*_config`; HardwareError names the limit a value exceeds). Fields left
    None keep the driver's default; the ports given replace the scenario's; the Z1 client
    follows each target over the control period (its `command_period_s`)."""
    from dexdrake.hardware.allegro_can import AllegroConfig, check_allegro_config
    from dexdrake.hardware.z1_udp import ArmFSMState, Z1Config, check_z1_config

    def given(**kw):
        return {k: v for k, v in kw.items() if v is not None}

    h, a = s.drivers.hand, s.drivers.arm
    hand = AllegroConfig(**given(kp=h.kp, kd=h.kd, pwm_limit=h.pwm_limit, lower=h.lower, upper=h.upper,
                                 max_target_rate=h.max_target_rate, limit_margin_rad=h.limit_margin_rad,
                                 watchdog_timeout_s=h.watchdog_timeout_s, status_timeout_s=h.status_timeout_s,
                                 temperature_timeout_s=h.temperature_timeout_s))
    arm = Z1Config(**given(host=a.host, local_port=a.local_port if arm_local_port is None else arm_local_port,
                           controller_port=a.controller_port if arm_controller_port is None
                           else arm_controller_port,
                           watchdog_timeout_s=a.watchdog_timeout_s, mode=ArmFSMState[a.mode],
                           kp=a.kp, kd=a.kd, max_velocity=a.max_velocity, limit_margin_rad=a.limit_margin_rad,
                           velocity_feedforward=a.velocity_feedforward), command_period_s=s.control_period)
    check_allegro_config(hand)
    check_z1_config(arm)
    return hand, arm


def simulated(s: Scenario) -> Scenario:
    """`s` with simulated drivers (their limits kept) and the ground-truth camera: its sim
    station, and the model of a hil/real station's robot and object for kinematics and for
    mirroring its measurements."""
    d = s.drivers
    return dc.replace(s, drivers=Drivers(hand=dc.replace(d.hand, kind="sim"), arm=dc.replace(d.arm, kind="sim")))


def validate_scenario(s: Scenario, source: str = "<scenario>") -> None:
    """Raise ScenarioError unless `s` describes a station that can be built."""
    from dexdrake.hands.description import load_hand
    from dexdrake.objects.library import get_object

    try:
        hand = load_hand(s.hand)
        get_object(s.object)
    except DexdrakeError as err:
        raise ScenarioError(f"{source}: {err}") from None
    _require(s.seed >= 0, source, f"seed must be at least 0, got {s.seed}")
    _require(s.time_step > 0 and math.isfinite(s.time_step), source,
             f"time_step must be > 0, got {s.time_step}")
    _require(s.contact_approximation in CONTACT_APPROXIMATIONS, source,
             f"contact_approximation {s.contact_approximation!r} is not one of {', '.join(CONTACT_APPROXIMATIONS)}")
    _require(s.control_period >= s.time_step, source,
             f"control_period ({s.control_period}) must be >= time_step ({s.time_step})")
    _require(is_multiple(s.control_period, s.time_step), source,
             f"control_period ({s.control_period}) must be a whole multiple of time_step "
             f"({s.time_step}): the controller runs every control_period and the plant steps "
             "by time_step, so a remainder stalls the loop")
    h, a, c = s.drivers.hand, s.drivers.arm, s.drivers.camera
    for name, kind, valid in (("drivers.hand.kind", h.kind, HAND_KINDS),
                              ("drivers.arm.kind", a.kind, HAND_KINDS),
                              ("drivers.camera.kind", c.kind, CAMERA_KINDS)):
        _require(kind in valid, source, f"{name} {kind!r} is not one of {', '.join(valid)}")
    _require(h.kind == a.kind, source,
             f"drivers.hand.kind ({h.kind}) and drivers.arm.kind ({a.kind}) must match: "
             "the hand's policy joints span the arm and the hand")
    mode = s.mode
    emulated_process = h.kind in EMULATED_PROCESS_KINDS
    cameras = {"sim": ("sim",), "hil": ("sim", "rendered"),
               "real": {"emulated_process": ("recorded", "rendered"), "emulated_world": ("rendered",)}.get(
                   h.kind, ("k4a", "recorded"))}[mode]
    _require(c.kind in cameras, source,
             f"drivers.camera.kind {c.kind!r} is not available in {mode} mode "
             f"(use one of {', '.join(cameras)})")
    if mode != "sim":
        _require(hand.hardware_joints is not None and len(hand.arm_joints) == NUM_ARM_JOINTS
                 and len(hand.hardware_joints) == NUM_HAND_JOINTS, source,
                 f"hand {s.hand!r} has no Allegro-on-Z1 hardware layout; {mode} mode needs "
                 "one (e.g. allegro_z1)")
        _require(0 <= h.device_id <= 3, source, f"drivers.hand.device_id must be 0..3, got {h.device_id}")
        _require(bool(h.interface) and bool(h.channel), source,
                 "drivers.hand.interface and .channel must be set")
        _require(h.port is None or 1 <= h.port <= 65535 or (h.port == 0 and emulated_process), source,
                 f"drivers.hand.port {h.port} is not a UDP port (0, a free one, only with "
                 f"{' or '.join(EMULATED_PROCESS_KINDS)})")
        _require(not emulated_process or h.interface != "virtual", source,
                 f"drivers.hand.interface 'virtual' does not cross processes; an {h.kind} hand "
                 "needs a bus that does (udp_multicast)")
        _require((h.lower is None) == (h.upper is None), source,
                 "drivers.hand.lower and .upper must be given together")
        for name, entry in (("hand", h), ("arm", a)):
            _require(not (entry.process and entry.kind == "emulated"), source,
                     f"drivers.{name}.process: the simulated-clock HIL (kind emulated) runs its "
                     "drivers in-process, in lockstep with its world")
            p = entry.realtime_priority
            _require(p is None or (own_process(entry) and 1 <= p <= 99), source,
                     f"drivers.{name}.realtime_priority {p}: 1..99, for a driver in its own process")
            _require(entry.heartbeat_timeout_s is None or own_process(entry), source,
                     f"drivers.{name}.heartbeat_timeout_s: only a driver in its own process has a "
                     "parent's heartbeat to watch")
            try:
                process_config(entry)
            except DexdrakeError as err:
                raise ScenarioError(f"{source}: drivers.{name}.{err}") from None
        _require(a.mode in ARM_MODES, source, f"drivers.arm.mode {a.mode!r} is not one of {', '.join(ARM_MODES)}")
        for name in ("local_port", "controller_port"):
            port = getattr(a, name)
            _require(port is None or 0 <= port <= 65535, source,
                     f"drivers.arm.{name} {port} is not a UDP port")
            _require(port != 0 or a.kind != "hardware", source,
                     f"drivers.arm.{name} 0 (a free port) is only allowed with an emulated arm")
        try:  # the drivers' own checks against the model's and the vendor's limits
            driver_configs(s)
        except DexdrakeError as err:
            raise ScenarioError(f"{source}: drivers: {err}") from None
    if c.kind != "sim":
        _require(c.width > 0 and c.height > 0, source, f"camera size {c.width}x{c.height} is invalid")
        _check_vector(c.intrinsics, 4, "drivers.camera.intrinsics", source)
        _check_vector(c.eye, 3, "drivers.camera.eye", source)
        _check_vector(c.target, 3, "drivers.camera.target", source)
        _require(c.period_s > 0 and c.first_pose_timeout_s > 0 and c.max_consecutive_failures >= 1,
                 source, "drivers.camera.period_s, .first_pose_timeout_s must be > 0 and "
                 ".max_consecutive_failures >= 1")
        _require(c.predict_s >= 0, source, f"drivers.camera.predict_s must be >= 0 (s), got {c.predict_s}")
        _require(c.period_s <= c.hold_pose_age_s <= c.max_pose_age_s, source,
                 f"drivers.camera: need period_s ({c.period_s}) <= hold_pose_age_s ({c.hold_pose_age_s}) "
                 f"<= max_pose_age_s ({c.max_pose_age_s}): a pose is at least one period old when the "
                 "next one comes; the station holds before it stops")
        _require(c.on_failure in PERCEPTION_FAILURE_POLICIES, source,
                 f"drivers.camera.on_failure {c.on_failure!r} is not one of "
                 f"{', '.join(PERCEPTION_FAILURE_POLICIES)}")
        _require(c.kind != "recorded" or bool(c.recording), source,
                 "drivers.camera.recording must name a folder or .npz for kind 'recorded'")
    r = s.real
    _require(r.horizon >= 1 and r.move_speed > 0 and r.move_tolerance > 0 and r.move_timeout_s > 0, source,
             "real.horizon must be >= 1 and real.move_speed, .move_tolerance, .move_timeout_s > 0")
    _check_vector(r.workspace_lower, 3, "real.workspace_lower", source)
    _check_vector(r.workspace_upper, 3, "real.workspace_upper", source)
    _require(all(lo < hi for lo, hi in zip(r.workspace_lower, r.workspace_upper)), source,
             f"real.workspace_lower {r.workspace_lower} must be below real.workspace_upper {r.workspace_upper}")
    problems = s.perception.problems(s.control_period)
    _require(not problems, source, "perception." + "; perception.".join(problems))
    w = s.hil
    _require(w.pwm_torque_scale > 0 and w.max_lag_s > 0 and w.reply_timeout_s > 0, source,
             "hil.pwm_torque_scale, .max_lag_s and .reply_timeout_s must be > 0")
    if s.policy is not None:
        from dexdrake.dexrep.feature_sets import FEATURE_SETS, PATHS

        _require(bool(s.policy.checkpoint), source,
                 "policy.checkpoint must name a policy file (remove the policy entry for the "
                 "scripted grasp)")
        _require(s.policy.feature_set in FEATURE_SETS, source,
                 f"policy.feature_set {s.policy.feature_set!r} is not one of "
                 f"{', '.join(sorted(FEATURE_SETS))}")
        _require(s.policy.feature_path in PATHS, source,
                 f"policy.feature_path {s.policy.feature_path!r} is not one of {', '.join(PATHS)}")
        _require(s.policy.feature_path != "scenegraph" or mode == "sim", source,
                 f"policy.feature_path 'scenegraph' needs the simulated object's SceneGraph; in {mode} "
                 "mode the object is known by its perceived pose: use 'fast' (that pose and the "
                 "object's geometry)")
