"""Z1 wire structs, UDP client and emulated controller on loopback (ephemeral ports)."""

import math
import socket
import struct
import time

import numpy as np
import pytest

from dexdrake.hardware.safety import HardwareError
from dexdrake.hardware.z1_emulator import Z1Emulator, Z1EmulatorConfig, flange_posture
from dexdrake.hardware.z1_udp import (
    JOINT_CMD_SIZE,
    JOINT_STATE_SIZE,
    RECV_STATE_SIZE,
    SEND_CMD_SIZE,
    ArmFSMState,
    JointCmd,
    JointState,
    MotorState,
    OfficialZ1,
    PacketError,
    RecvState,
    SendCmd,
    Z1Arm,
    Z1Config,
    default_joint_limits,
    free_udp_port,
)
from waiting import wait_for

# z1.md, current limits
LOWER = np.array([-2.6180, 0.0, -2.8798, -1.5184, -1.3439, -2.7925])
UPPER = np.array([2.6180, 2.9671, 0.0, 1.5184, 1.3439, 2.7925])
TARGET = np.array([0.5, 1.0, -1.0, 0.3, -0.3, 0.5])


def new_emulator(**kw) -> Z1Emulator:
    """An emulator on a free port that sends to a free client port (probed: `client_port`)."""
    kw.setdefault("lower", LOWER)
    kw.setdefault("upper", UPPER)
    return Z1Emulator(Z1EmulatorConfig(port=0, client_port=free_udp_port(), **kw))


@pytest.fixture
def emulator():
    emu = new_emulator()
    emu.start()
    yield emu
    emu.stop()


def make_arm(emu: Z1Emulator, **kw) -> Z1Arm:
    # a watchdog generous enough for a loaded 2-core CI machine; stalls below are longer
    kw.setdefault("watchdog_timeout_s", 0.2)
    return Z1Arm(Z1Config(local_port=emu.config.client_port, controller_port=emu.port, lower=LOWER,
                          upper=UPPER, **kw))


class RawClient:
    """A bare UDP socket on the emulator's client port speaking SendCmd/RecvState."""

    def __init__(self, emu: Z1Emulator):
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.bind(("127.0.0.1", emu.config.client_port))
        self.sock.settimeout(0.5)
        self.port = emu.port

    def send(self, cmd: SendCmd | bytes) -> RecvState:
        self.sock.sendto(cmd if isinstance(cmd, bytes) else cmd.pack(), ("127.0.0.1", self.port))
        return RecvState.unpack(self.sock.recv(4096))

    def close(self) -> None:
        self.sock.close()


# ------------------------------------------------------------------ structs
def test_struct_sizes_match_spec():
    assert (JOINT_CMD_SIZE, SEND_CMD_SIZE, JOINT_STATE_SIZE, RECV_STATE_SIZE) == (20, 147, 22, 208)
    assert len(SendCmd(ArmFSMState.PASSIVE).pack()) == 147
    assert len(RecvState(ArmFSMState.PASSIVE).pack()) == 208


def test_enum_is_in_header_order():
    names = ["INVALID", "PASSIVE", "JOINTCTRL", "CARTESIAN", "MOVEJ", "MOVEL", "MOVEC",
             "TRAJECTORY", "TOSTATE", "SAVESTATE", "TEACH", "TEACHREPEAT", "CALIBRATION",
             "SETTRAJ", "BACKTOSTART", "NEXT", "LOWCMD"]
    assert [s.name for s in ArmFSMState] == names and ArmFSMState.LOWCMD == 16


def test_round_trips_and_layout():
    jc = JointCmd(T=1.5, W=-0.25, Pos=0.75, K_P=20.0, K_W=2000.0)
    assert JointCmd.unpack(jc.pack()) == jc
    assert jc.pack() == struct.pack("<5f", 1.5, -0.25, 0.75, 20.0, 2000.0)
    cmd = SendCmd(ArmFSMState.LOWCMD, (jc,) * 7, track=True, head=(1, 2))
    raw = cmd.pack()
    assert raw[:2] == b"\x01\x02" and raw[2:6] == (16).to_bytes(4, "little") and raw[6] == 1
    assert raw[7:27] == jc.pack()
    assert SendCmd.unpack(raw) == cmd
    js = JointState(T=2.0, W=0.5, Acc=-1.0, Pos=0.25,
                    motors=(MotorState(40, 0x04, 0x40), MotorState(-5, 0, 0)))
    assert JointState.unpack(js.pack()) == js and js.motors[0].link == 1
    st = RecvState(ArmFSMState.JOINTCTRL, (js,) * 7, (0.1, 0.2, 0.3, 0.4, 0.5, 0.75), head=(3, 4))
    raw = st.pack()
    assert struct.unpack_from("<6d", raw, 208 - 48) == st.posture
    assert RecvState.unpack(raw) == st


NAN_POSTURE = RecvState(ArmFSMState.PASSIVE).pack()[:-8] + struct.pack("<d", math.nan)


@pytest.mark.parametrize("make, kind, detail", [
    (lambda: SendCmd.unpack(b"\x00" * 146), "size", "SendCmd is 147 bytes, got 146"),
    (lambda: RecvState.unpack(b"\x00" * 209), "size", "RecvState is 208 bytes, got 209"),
    (lambda: JointCmd.unpack(b"\x00" * 19), "size", "JointCmd is 20 bytes, got 19"),
    (lambda: JointState.unpack(b"\x00" * 23), "size", "JointState is 22 bytes, got 23"),
    (lambda: SendCmd(ArmFSMState.PASSIVE, (JointCmd(),) * 6).pack(), "size", "SendCmd needs 7 JointCmd, got 6"),
    (lambda: RecvState(ArmFSMState.PASSIVE, posture=(0.0,) * 5).pack(), "size",
     "RecvState needs 7 joint states and a 6-value posture"),
    (lambda: SendCmd.unpack(b"\x00\x00" + (17).to_bytes(4, "little") + b"\x00" * 141), "enum",
     "ArmFSMState 17 outside 0..16"),
    (lambda: RecvState.unpack(b"\x00\x00" + (2**31 - 1).to_bytes(4, "little") + b"\x00" * 202), "enum",
     "ArmFSMState 2147483647 outside 0..16"),
    (lambda: SendCmd.unpack(b"\x00\x00" + (1).to_bytes(4, "little") + b"\x02" + b"\x00" * 140), "range",
     "SendCmd track byte 2 is not a bool"),
    (lambda: SendCmd.unpack(b"\x00\x00" + (1).to_bytes(4, "little") + b"\x00"
                            + struct.pack("<5f", math.nan, 0, 0, 0, 0) + b"\x00" * 120), "nonfinite",
     "JointCmd has non-finite values (nan, 0.0, 0.0, 0.0, 0.0)"),
    (lambda: JointCmd(Pos=math.inf).pack(), "nonfinite", "JointCmd has non-finite values (0.0, 0.0, inf, 0.0, 0.0)"),
    (lambda: JointState(Acc=math.nan).pack(), "nonfinite", "JointState has non-finite values (0.0, 0.0, nan, 0.0)"),
    (lambda: RecvState(ArmFSMState.PASSIVE, posture=(0.0,) * 5 + (math.inf,)).pack(), "nonfinite",
     "posture has non-finite values (0.0, 0.0, 0.0, 0.0, 0.0, inf)"),
    (lambda: RecvState.unpack(NAN_POSTURE), "nonfinite", "posture has non-finite values (0.0, 0.0, 0.0, 0.0, 0.0, nan)"),
    (lambda: JointState(motors=(MotorState(temperature=300), MotorState())).pack(), "range", "motor state"),
])
def test_validation_errors(make, kind, detail):
    with pytest.raises(PacketError) as err:
        make()
    assert err.value.kind == kind
    assert str(err.value).startswith(f"bad Z1 packet ({kind}): {detail}"), str(err.value)


def test_default_limits_from_description():
    lo, hi = default_joint_limits()
    np.testing.assert_allclose(lo, LOWER, atol=1e-4)
    np.testing.assert_allclose(hi, UPPER, atol=1e-4)


# ------------------------------------------------------------------ emulator FSM
def test_emulator_fsm_rules(emulator):
    c = RawClient(emulator)
    try:
        assert c.send(SendCmd(ArmFSMState.PASSIVE)).state == ArmFSMState.PASSIVE
        assert c.send(SendCmd(ArmFSMState.MOVEJ)).state == ArmFSMState.PASSIVE  # not emulated
        assert c.send(SendCmd(ArmFSMState.JOINTCTRL)).state == ArmFSMState.JOINTCTRL
        assert c.send(SendCmd(ArmFSMState.LOWCMD)).state == ArmFSMState.JOINTCTRL  # not from here
        assert c.send(SendCmd(ArmFSMState.PASSIVE)).state == ArmFSMState.PASSIVE
        assert c.send(SendCmd(ArmFSMState.LOWCMD)).state == ArmFSMState.LOWCMD
        assert c.send(SendCmd(ArmFSMState.JOINTCTRL)).state == ArmFSMState.LOWCMD  # only to PASSIVE
        assert emulator.rejected_transitions == {"PASSIVE->MOVEJ": 1, "JOINTCTRL->LOWCMD": 1,
                                                 "LOWCMD->JOINTCTRL": 1}
        # silence in LOWCMD changes nothing: the controller keeps executing the last command
        time.sleep(0.3)
        assert emulator.fsm == ArmFSMState.LOWCMD
        # garbage is counted, not answered
        c.sock.sendto(b"\x01\x02\x03", ("127.0.0.1", emulator.port))
        assert wait_for(lambda: emulator.packet_errors["size"] == 1, 1.0)
    finally:
        c.close()


def test_emulator_lowcmd_torque_law(emulator):
    """The reported torque equals kp*25.6*(q_d - q) + kd*0.0128*(dq_d - dq) + tau_ff, each
    term large enough that dropping it (or a wrong scale) fails: kp term about 5 N*m, kd
    term about 1.3 N*m, tau_ff 0.5 N*m, all under the 30 N*m effort limit."""
    c = RawClient(emulator)
    try:
        c.send(SendCmd(ArmFSMState.LOWCMD))
        q_d, dq_d, kp, kd, tau_ff = 0.2, 1.0, 1.0, 100.0, 0.5
        cmd = SendCmd(ArmFSMState.LOWCMD,
                      (JointCmd(T=tau_ff, W=dq_d, Pos=q_d, K_P=kp, K_W=kd),) * 6 + (JointCmd(),))
        st = c.send(cmd)
        for i in (0, 4):  # joints with no gravity load at q = 0: they start at rest
            j = st.joints[i]
            kp_term, kd_term = kp * 25.6 * (q_d - j.Pos), kd * 0.0128 * (dq_d - j.W)
            assert kp_term > 3.0 and kd_term > 0.3
            assert j.T == pytest.approx(kp_term + kd_term + tau_ff, abs=1e-3)
    finally:
        c.close()


def test_emulator_dynamics_hook_gets_the_command_and_reports_its_state():
    """A custom ArmDynamics is stepped with the controller's command; replies carry its state."""
    from dexdrake.hardware.z1_emulator import ArmCommand

    class Fixed:
        def __init__(self):
            self.commands: list[ArmCommand] = []

        def step(self, command, dt):
            self.commands.append(command)
            return TARGET.copy(), np.full(6, 0.25), np.full(6, -1.5)

    dynamics = Fixed()
    emu = Z1Emulator(Z1EmulatorConfig(port=0, client_port=free_udp_port(), lower=LOWER, upper=UPPER),
                     dynamics=dynamics)
    emu.start()
    c = RawClient(emu)
    try:
        c.send(SendCmd(ArmFSMState.LOWCMD))
        cmd = SendCmd(ArmFSMState.LOWCMD, (JointCmd(T=0.5, W=0.1, Pos=0.2, K_P=3.0, K_W=40.0),) * 6
                      + (JointCmd(),))
        c.send(cmd)
        assert wait_for(lambda: dynamics.commands[-1].fsm == ArmFSMState.LOWCMD
                        and dynamics.commands[-1].q_d[0] == pytest.approx(0.2), 1.0)
        last = dynamics.commands[-1]
        np.testing.assert_allclose([last.dq_d[5], last.tau_ff[5], last.kp[5], last.kd[5]],
                                   [0.1, 0.5, 3.0, 40.0], rtol=1e-6)
        st = c.send(cmd)
        np.testing.assert_allclose([j.Pos for j in st.joints[:6]], TARGET, rtol=1e-6)
        np.testing.assert_allclose([j.W for j in st.joints[:6]], 0.25)
    finally:
        c.close()
        emu.stop()


# ------------------------------------------------------------------ client
@pytest.mark.parametrize("mode", [ArmFSMState.LOWCMD, ArmFSMState.JOINTCTRL])
def test_client_tracks_target(emulator, mode):
    arm = make_arm(emulator, mode=mode)
    with arm:
        assert arm.state().fsm == mode and emulator.fsm == mode
        arm.command_positions(TARGET)
        assert wait_for(lambda: np.max(np.abs(emulator.q - TARGET)) < 0.01, 3.0), arm.stats()
        assert wait_for(lambda: np.max(np.abs(arm.state().q - TARGET)) < 0.01, 1.0)
        st = arm.state()
        assert st.fault is None
        stats = arm.stats()
        assert stats["cycles"] > 10 and stats["max_ms"] >= stats["p99_ms"] >= stats["p50_ms"] > 0
    assert wait_for(lambda: emulator.fsm == ArmFSMState.PASSIVE, 1.0)


def test_state_reports_the_measured_joints_and_posture(emulator):
    """Before start: INVALID and NaN everywhere, the target held at the clamped zero. While
    moving toward UPPER: joint velocities of that sign; at rest: the gravity torques the
    arm holds, the flange posture of the reported q, a fresh time stamp."""
    from dexdrake.hardware.z1_model import z1_model

    arm = make_arm(emulator)
    st = arm.state()
    assert st.fsm == ArmFSMState.INVALID and math.isnan(st.t) and st.fault is None
    for v, n in ((st.q, 6), (st.dq, 6), (st.tau, 6), (st.posture, 6)):
        assert v.shape == (n,) and np.all(np.isnan(v))
    np.testing.assert_array_equal(st.q_target, np.clip(0.0, LOWER + 0.02, UPPER - 0.02))  # the margin
    stats = arm.stats()
    assert stats["packets_received"] == 0 and stats["cycles"] == 0 and stats["packet_errors"] == {}
    with arm:
        arm.command_positions(UPPER)
        assert wait_for(lambda: np.min(arm.state().dq[[0, 1, 3, 4, 5]]) > 0.2, 2.0), arm.state().dq
        arm.command_positions(TARGET)
        assert wait_for(lambda: np.max(np.abs(arm.state().q - TARGET)) < 0.002, 4.0)
        time.sleep(0.1)
        st = arm.state()
        assert time.monotonic() - 0.1 < st.t <= time.monotonic()
        np.testing.assert_allclose(st.dq, 0.0, atol=0.01)
        np.testing.assert_allclose(st.tau, z1_model().gravity(TARGET), atol=0.05)
        np.testing.assert_allclose(st.posture, flange_posture(st.q), atol=1e-5)  # q is float32 on the wire
        np.testing.assert_allclose(st.q_target, TARGET)
        stats = arm.stats()
        assert stats["packets_received"] > 10 and stats["packet_errors"] == {}
        assert stats["fault"] is None and stats["torque_clamped"] == 0


def test_velocity_limit_on_targets(emulator):
    """The target moves toward a far command no faster than the limit on targets (the driver's
    default, 2 rad/s) allows in the elapsed time, and is not stuck (on a loaded machine the loop may
    run late, which only slows it)."""
    arm = make_arm(emulator)
    with arm:
        start = arm.state().q_target
        t0 = time.monotonic()
        arm.command_positions(UPPER)  # joint 1 is commanded 2.6 rad away: 1.3 s at 2 rad/s
        assert wait_for(lambda: np.max(np.abs(arm.state().q_target - start)) >= 0.05 * math.pi, 5.0)
        time.sleep(0.1)
        step = np.max(np.abs(arm.state().q_target - start))
        elapsed = time.monotonic() - t0
        assert 0.05 * math.pi <= step <= Z1Config().max_velocity * elapsed + 0.01, (step, elapsed)


def test_nan_and_out_of_range_targets(emulator):
    arm = make_arm(emulator)
    with arm:
        np.testing.assert_allclose(arm.command_positions(TARGET), TARGET)
        np.testing.assert_allclose(arm.command_positions([math.nan] * 6), TARGET)
        np.testing.assert_allclose(arm.command_positions(np.full(6, 9.0)), UPPER - 0.02)  # the margin
        assert arm.stats()["rejected_commands"] == 1 and arm.stats()["clamped_commands"] == 1
        with pytest.raises(HardwareError):
            arm.command_positions(np.zeros(5))
        assert wait_for(lambda: np.max(np.abs(emulator.q - UPPER + 0.02)) < 0.01, 4.0)


def test_watchdog_latches_passive_until_reset(emulator):
    arm = make_arm(emulator)
    with arm:
        emulator.stall(0.6)
        assert wait_for(lambda: arm.state().fault is not None, 1.0)
        assert "no Z1 state" in arm.state().fault
        assert wait_for(lambda: emulator.fsm == ArmFSMState.PASSIVE, 0.5)
        time.sleep(0.6)  # replies are back; the fault stays latched and the arm PASSIVE
        assert arm.state().fault is not None and emulator.fsm == ArmFSMState.PASSIVE
        arm.reset_fault()
        assert wait_for(lambda: arm.state().fault is None and emulator.fsm == ArmFSMState.LOWCMD, 1.0)
        arm.command_positions(TARGET)
        assert wait_for(lambda: np.max(np.abs(emulator.q - TARGET)) < 0.01, 3.0), arm.stats()


def test_motor_error_trips(emulator):
    arm = make_arm(emulator)
    with arm:
        emulator.motor_error = (2, 0x04)
        assert wait_for(lambda: arm.state().fault is not None, 1.0)
        assert "joint3" in arm.state().fault and arm.stats()["fault"] == arm.state().fault
        assert wait_for(lambda: emulator.fsm == ArmFSMState.PASSIVE, 0.5)


def test_malformed_packets_are_counted(emulator):
    arm = make_arm(emulator)
    with arm:
        junk = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        try:
            for payload in (b"", b"\x00" * 7, b"\xff" * 208, b"\x00" * 300):
                junk.sendto(payload, ("127.0.0.1", arm.local_port))
        finally:
            junk.close()
        assert wait_for(lambda: sum(arm.stats()["packet_errors"].values()) >= 3, 1.0)
        assert arm.running and arm.state().fault is None
        emulator.corrupt_replies = True  # every reply bad: errors counted, then the watchdog
        assert wait_for(lambda: arm.state().fault is not None, 1.0)
        errors = arm.stats()["packet_errors"]
        assert {"size", "enum", "nonfinite"} & set(errors), errors
        assert arm.running


def test_restart_holds_where_the_arm_is_not_the_old_target(emulator):
    """A second session starts from the measured position: the first one's target and
    reference are forgotten, so the arm does not jump back to them."""
    arm = make_arm(emulator)
    with arm:
        arm.command_positions(TARGET)
        assert wait_for(lambda: np.max(np.abs(emulator.q - TARGET)) < 0.01, 3.0)
    # PASSIVE: the unheld arm sags away from TARGET under gravity
    assert wait_for(lambda: np.max(np.abs(emulator.q - TARGET)) > 0.3, 3.0)
    with arm:
        q_start = arm.state().q
        assert np.max(np.abs(q_start - TARGET)) > 0.3
        time.sleep(0.3)
        np.testing.assert_allclose(arm.state().q_target, q_start, atol=0.05)
        np.testing.assert_allclose(emulator.q, q_start, atol=0.05)


def quiet_emulator() -> Z1Emulator:
    """A running emulator (it never drops to PASSIVE on its own: what it does, the client asked)."""
    emu = new_emulator()
    emu.start()
    return emu


def test_stop_commands_passive_and_closes_the_socket():
    emu = quiet_emulator()
    try:
        arm = make_arm(emu)
        with arm:
            assert emu.fsm == ArmFSMState.LOWCMD
        assert wait_for(lambda: emu.fsm == ArmFSMState.PASSIVE, 0.5)  # told: it never times out
        with pytest.raises(HardwareError, match="Z1: not started"):
            arm.local_port
    finally:
        emu.stop()


@pytest.mark.filterwarnings("ignore::pytest.PytestUnhandledThreadExceptionWarning")
def test_a_crashing_loop_latches_a_fault_and_commands_passive():
    emu = quiet_emulator()
    try:
        arm = make_arm(emu)
        with arm:
            def broken(dt):
                raise RuntimeError("bug in the loop")

            arm._command = broken
            assert wait_for(lambda: arm.state().fault is not None, 1.0)
            assert arm.state().fault == "client loop failed: RuntimeError('bug in the loop')"
            assert wait_for(lambda: emu.fsm == ArmFSMState.PASSIVE, 0.5)
            assert wait_for(lambda: not arm.running, 0.5)
    finally:
        emu.stop()


def test_reset_after_a_fault_holds_where_the_arm_fell(emulator):
    """While faulted the arm is PASSIVE and sags; reset_fault() re-enters the mode holding
    that measured position: no jump back to the old reference or target."""
    arm = make_arm(emulator)
    with arm:
        arm.command_positions(TARGET)
        assert wait_for(lambda: np.max(np.abs(emulator.q - TARGET)) < 0.01, 3.0)
        emulator.stall(0.3)
        assert wait_for(lambda: arm.state().fault is not None, 1.0)
        ms = float(arm.state().fault.split()[-2])
        assert 200 <= ms < 5000, arm.state().fault  # the silence, in ms (watchdog 0.2 s)
        assert wait_for(lambda: np.max(np.abs(emulator.q - TARGET)) > 0.3, 3.0)  # sagged, PASSIVE
        time.sleep(0.3)  # replies are back
        arm.reset_fault()
        assert wait_for(lambda: arm.state().fault is None and emulator.fsm == ArmFSMState.LOWCMD, 1.0)
        q_reset = arm.state().q
        assert np.max(np.abs(q_reset - TARGET)) > 0.3
        time.sleep(0.3)
        np.testing.assert_allclose(arm.state().q_target, q_reset, atol=0.05)
        np.testing.assert_allclose(emulator.q, q_reset, atol=0.05)


def test_commands_stay_inside_the_configured_limits_when_the_arm_starts_outside():
    """The arm rests beyond a lowered limit: the reference starts clamped into the limits
    and no command ever leaves them."""
    emu = Z1Emulator(Z1EmulatorConfig(port=0, client_port=free_udp_port(), lower=LOWER, upper=UPPER, gravity=False,
                                      q0=[0.55, 0.95, -0.95, 0.0, 0.0, 0.0]))
    emu.start()
    lower, upper = LOWER.copy(), UPPER.copy()
    upper[0], lower[1], upper[2] = 0.5, 1.0, -1.0
    try:
        arm = Z1Arm(Z1Config(local_port=emu.config.client_port, controller_port=emu.port, lower=lower, upper=upper,
                             watchdog_timeout_s=0.2))
        seen = []
        with arm:
            for _ in range(40):
                cmd = emu.command()
                if cmd.fsm == ArmFSMState.LOWCMD:
                    seen.append(cmd.q_d)
                time.sleep(0.005)
        seen = np.array(seen)
        assert len(seen) > 10
        assert np.all(seen >= lower - 1e-6) and np.all(seen <= upper + 1e-6), (seen.min(0), seen.max(0))
    finally:
        emu.stop()


def test_start_refusals_name_the_cause(emulator):
    arm = make_arm(emulator)
    with arm:
        with pytest.raises(HardwareError, match="Z1: already started"):
            arm.start()
        busy = arm.local_port
        with pytest.raises(HardwareError, match=f"Z1: cannot bind UDP 127.0.0.1:{busy}"):
            Z1Arm(Z1Config(local_port=busy, controller_port=emulator.port, lower=LOWER, upper=UPPER)).start()
        emulator.motor_error = (0, 0x01)
        assert wait_for(lambda: arm.state().fault is not None, 1.0)
    emulator.motor_error = None
    with pytest.raises(HardwareError, match=r"Z1: fault latched \(joint1 motor error 0x01 link 0\); call reset_fault"):
        arm.start()
    arm.reset_fault()  # stopped: only the latch clears
    time.sleep(0.2)  # a reply built with the error before it cleared (a preempted emulator thread) lands first
    with arm:
        assert arm.state().fault is None and emulator.fsm == ArmFSMState.LOWCMD


def test_given_velocity_is_fed_forward_within_the_limit(emulator):
    """LOWCMD: a caller's dq goes out as the joints' W, clipped to +-max_velocity; without
    one the reference's own velocity (zero at rest) is sent. Bad dq / tau_ff are refused."""
    arm = make_arm(emulator, max_velocity=2.0)
    with arm:
        dq = np.array([10.0, -10.0, 1.0, -1.0, 0.0, 0.5])
        arm.command_positions(np.zeros(6), dq=dq)
        assert wait_for(lambda: np.allclose(emulator.command().dq_d, np.clip(dq, -2.0, 2.0), atol=1e-6), 1.0), \
            emulator.command().dq_d
        arm.command_positions(np.zeros(6))
        assert wait_for(lambda: np.allclose(emulator.command().dq_d, 0.0, atol=1e-6), 1.0)
        for bad in ({"dq": [math.nan] * 6}, {"dq": [0.0] * 5}, {"tau_ff": [math.inf] * 6}):
            with pytest.raises(HardwareError, match=f"Z1 {next(iter(bad))}: need 6 finite values"):
                arm.command_positions(np.zeros(6), **bad)


def test_reference_velocity_is_sent_only_with_velocity_feedforward(emulator):
    """While the rate-limited reference ramps, its velocity goes out as W; with
    velocity_feedforward off W stays zero (the arm's PD damps towards rest)."""
    for ff in (True, False):
        arm = make_arm(emulator, max_velocity=1.0, velocity_feedforward=ff)
        sent = []
        with arm:
            q = arm.state().q  # 0.5 s of ramp towards the middle of each joint's range
            target = q + 0.5 * np.sign((LOWER + UPPER) / 2 - q)
            arm.command_positions(target)
            assert wait_for(lambda: sent.append(emulator.command().dq_d.copy())
                            or np.abs(arm.state().q_target - target).max() < 1e-6, 5.0)
        emulator.stall(0)  # back to PASSIVE between the two runs
        assert wait_for(lambda: emulator.fsm == ArmFSMState.PASSIVE, 1.0)
        peak = np.abs(sent).max()
        assert (peak == pytest.approx(1.0, abs=1e-3)) if ff else peak == 0.0, (ff, peak)


def test_a_command_period_spreads_each_target_over_it(emulator):
    """With command_period_s the reference reaches a new target in that period, at a
    constant velocity sent as W (0.05 rad over 0.2 s: 0.25 rad/s), not at max_velocity;
    a target too far for the period still ramps at max_velocity."""
    arm = make_arm(emulator, max_velocity=1.0, command_period_s=0.2)
    with arm:
        q = arm.state().q
        toward_middle = np.sign((LOWER + UPPER) / 2 - q)
        for step, rate in ((0.05, 0.25), (0.5, 1.0)):
            sent, target = [], arm.state().q_target + step * toward_middle
            arm.command_positions(target)
            assert wait_for(lambda: sent.append(emulator.command().dq_d.copy())
                            or np.abs(arm.state().q_target - target).max() < 1e-6, 5.0)
            assert np.abs(sent).max() == pytest.approx(rate, abs=1e-3), (step, np.abs(sent).max())


def test_start_without_controller_fails_cleanly():
    free = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    free.bind(("127.0.0.1", 0))
    port = free.getsockname()[1]
    free.close()
    arm = Z1Arm(Z1Config(local_port=0, controller_port=port, lower=LOWER, upper=UPPER,
                          mode_timeout_s=0.3, watchdog_timeout_s=1.0))
    with pytest.raises(HardwareError, match=r"^Z1: start failed: controller did not enter LOWCMD "
                                            rf"\(is z1_controller running on 127.0.0.1:{port}\?\)$"):
        arm.start()
    assert not arm.running
    arm = Z1Arm(Z1Config(local_port=0, controller_port=port, lower=LOWER, upper=UPPER, mode_timeout_s=0.3))
    with pytest.raises(HardwareError, match=r"start failed: no Z1 state for \d+ ms"):  # the watchdog first
        arm.start()


def test_official_backend_explains_missing_module():
    with pytest.raises(HardwareError) as err:
        OfficialZ1(lower=LOWER, upper=UPPER)
    assert str(err.value) == (
        "unitree_arm_interface is not importable: build it from Unitree's z1_sdk (pybind11, Python 3.8) "
        "and put its lib folder on sys.path, or use Z1Arm, which speaks the same UDP protocol")


class FakeSdk:
    """Stands in for Unitree's `unitree_arm_interface` binding: records every call."""

    class ArmFSMState:
        PASSIVE = "PASSIVE"

    def __init__(self, q, qd):
        sdk = self
        self.calls: list[tuple] = []

        class LowState:
            def getQ(self):
                return list(q)

            def getQd(self):
                return list(qd)

        class ArmInterface:
            def __init__(self, hasGripper):
                sdk.calls.append(("init", hasGripper))
                self.lowstate = LowState()

            def __getattr__(self, name):
                return lambda *args: sdk.calls.append((name, *args))

        self.ArmInterface = ArmInterface


def test_official_backend_clamps_and_passes_the_sdk_calls(monkeypatch):
    """With the vendor binding importable: LOWCMD from start(), targets clamped into the
    model's limits (NaN holds the last safe one), zeros for missing dq/tau, PASSIVE on stop."""
    q_now, qd_now = [0.1, 0.2, -0.3, 0.4, -0.5, 0.6], [0.01] * 6
    sdk = FakeSdk(q_now, qd_now)
    monkeypatch.setitem(__import__("sys").modules, "unitree_arm_interface", sdk)
    arm = OfficialZ1(has_gripper=True)
    assert sdk.calls == [("init", True)]
    np.testing.assert_allclose(arm.start(), q_now)
    assert sdk.calls[-1] == ("setFsmLowcmd",)
    q, qd = arm.step(np.full(6, 9.0))
    np.testing.assert_allclose(q, q_now)
    np.testing.assert_allclose(qd, qd_now)
    name, q_sent, dq_sent, tau_sent = sdk.calls[-2]
    assert name == "setArmCmd" and sdk.calls[-1] == ("sendRecv",)
    np.testing.assert_allclose(q_sent, UPPER, atol=1e-4)  # the model's limits
    np.testing.assert_array_equal(dq_sent, np.zeros(6))
    np.testing.assert_array_equal(tau_sent, np.zeros(6))
    arm.step([math.nan] * 6, dq=np.full(6, 0.5), tau=np.full(6, -2.0))
    _, q_sent, dq_sent, tau_sent = sdk.calls[-2]
    np.testing.assert_allclose(q_sent, UPPER, atol=1e-4)  # held
    np.testing.assert_array_equal(dq_sent, np.full(6, 0.5))
    np.testing.assert_array_equal(tau_sent, np.full(6, -2.0))
    arm.stop()
    assert sdk.calls[-2:] == [("loopOff",), ("setFsm", "PASSIVE")]
    arm = OfficialZ1(lower=LOWER + 0.5, upper=UPPER - 0.5)
    assert sdk.calls[-1] == ("init", False)  # no gripper unless asked
    arm.start()
    arm.step([math.nan] * 6)
    np.testing.assert_allclose(sdk.calls[-2][1], np.clip(q_now, LOWER + 0.5, UPPER - 0.5))  # start's q, clamped
    for name in ("dq", "tau"):
        with pytest.raises(HardwareError, match=f"Z1 {name}: need 6 finite values"):
            arm.step(np.zeros(6), **{name: [math.nan] * 6})
    # one bound given: it applies, the other comes from the model
    OfficialZ1(upper=UPPER - 0.5).step(np.full(6, 9.0))
    np.testing.assert_allclose(sdk.calls[-2][1], UPPER - 0.5)
    OfficialZ1(lower=LOWER + 0.5).step(np.full(6, -9.0))
    np.testing.assert_allclose(sdk.calls[-2][1], LOWER + 0.5)
    OfficialZ1(lower=LOWER + 0.5).step(np.full(6, 9.0))
    np.testing.assert_allclose(sdk.calls[-2][1], UPPER, atol=1e-4)


# ------------------------------------------------------------------ vendor wire rules
def test_default_ports_and_head_follow_the_vendor():
    """The SDK binds 8072 and sends to 8071 (z1_controller binds 8071); head FE FF."""
    from dexdrake.hardware.z1_udp import COMMAND_HEAD

    assert (Z1Config().local_port, Z1Config().controller_port) == (8072, 8071)
    assert (Z1EmulatorConfig().port, Z1EmulatorConfig().client_port) == (8071, 8072)
    assert COMMAND_HEAD == (0xFE, 0xFF) and SendCmd(ArmFSMState.PASSIVE).pack()[:2] == b"\xfe\xff"


@pytest.mark.parametrize("raw, kind", [
    (SendCmd(ArmFSMState.PASSIVE, head=(0xFE, 0xEF)).pack(), "head"),
    (SendCmd(ArmFSMState.PASSIVE).pack()[:146], "size"),
    (SendCmd(ArmFSMState.PASSIVE).pack() + b"\x00", "size"),
])
def test_emulator_drops_what_the_controller_drops_without_a_reply(emulator, raw, kind):
    c = RawClient(emulator)
    c.sock.settimeout(0.2)
    try:
        with pytest.raises(socket.timeout):
            c.send(raw)
        assert emulator.packet_errors[kind] == 1 and emulator.commands_received == 0
        assert c.send(SendCmd(ArmFSMState.PASSIVE)).state == ArmFSMState.PASSIVE  # a valid one answers
    finally:
        c.close()


def test_emulator_jointctrl_follows_targets_only_with_track(emulator):
    c = RawClient(emulator)
    try:
        c.send(SendCmd(ArmFSMState.JOINTCTRL))
        target = (JointCmd(Pos=0.4),) * 6 + (JointCmd(),)
        c.send(SendCmd(ArmFSMState.JOINTCTRL, target, track=False))
        assert emulator.command().q_d[0] == pytest.approx(0.0)
        c.send(SendCmd(ArmFSMState.JOINTCTRL, target, track=True))
        assert emulator.command().q_d[0] == pytest.approx(0.4)
    finally:
        c.close()


class Controller:
    """A bare socket in the controller's place: records what the client sends, answers
    each valid command with a PASSIVE -> requested-state reply."""

    def __init__(self):
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.bind(("127.0.0.1", 0))
        self.sock.settimeout(0.5)
        self.port = self.sock.getsockname()[1]

    def capture(self, n: int) -> list[bytes]:
        out = []
        while len(out) < n:
            data, addr = self.sock.recvfrom(4096)
            out.append(data)
            state = SendCmd.unpack(data).state
            self.sock.sendto(RecvState(state).pack(), addr)
        return out


@pytest.mark.parametrize("mode", [ArmFSMState.LOWCMD, ArmFSMState.JOINTCTRL])
def test_client_packets_pass_the_controller_checks(mode):
    import concurrent.futures as cf

    ctl = Controller()
    arm = Z1Arm(Z1Config(local_port=0, controller_port=ctl.port, mode=mode, watchdog_timeout_s=0.5))
    with cf.ThreadPoolExecutor(1) as pool:
        capture = pool.submit(ctl.capture, 40)
        try:
            arm.start()
            packets = capture.result(5.0)
        finally:
            arm.stop()
            ctl.sock.close()
    assert all(len(p) == 147 and p[:2] == b"\xfe\xff" for p in packets)
    cmds = [SendCmd.unpack(p) for p in packets]
    in_mode = [c for c in cmds if c.state == mode]
    assert in_mode and all(c.track == (mode == ArmFSMState.JOINTCTRL) for c in in_mode)


def settled(emulator: Z1Emulator, timeout: float = 5.0) -> np.ndarray:
    """The emulated arm's q once it has stopped moving: three 0.1 s windows in a row, each
    with commands arriving (both threads ran) and every joint moving less than 2e-5 rad."""
    end, still, q = time.monotonic() + timeout, 0, emulator.q
    while still < 3:
        assert time.monotonic() < end, "the arm did not settle"
        n0, q0 = emulator.commands_received, q
        time.sleep(0.1)
        q = emulator.q
        busy = emulator.commands_received - n0 >= 5
        still = still + 1 if busy and np.max(np.abs(q - q0)) < 2e-5 else 0
    return q


def test_lowcmd_gravity_feedforward_holds_the_arm_up(emulator):
    """The emulated arm weighs what the model says: without the feed-forward it sags by
    g/(kp*25.6) (about 0.012 rad on joint3 at TARGET), with it it holds the target."""
    from dexdrake.hardware.z1_model import z1_model

    model = z1_model()
    sag = np.abs(model.gravity(TARGET) / (model.limits.kp * 25.6))
    assert sag[2] > 0.01
    errors = {}
    for ff in (False, True):
        arm = make_arm(emulator, gravity_feedforward=ff)
        with arm:
            arm.command_positions(TARGET)
            assert wait_for(lambda: np.max(np.abs(emulator.q - TARGET)) < 0.03, 4.0)
            errors[ff] = np.abs(settled(emulator) - TARGET)
        emulator.stall(0)  # back to PASSIVE between the two runs
        assert wait_for(lambda: emulator.fsm == ArmFSMState.PASSIVE, 1.0)
    np.testing.assert_allclose(errors[False][1:4], sag[1:4], rtol=0.2)
    assert np.max(errors[True]) < 0.002


def test_feedforward_torque_is_capped_by_the_effort_limits(emulator):
    from dexdrake.hardware.z1_model import z1_model

    effort = z1_model().limits.effort
    arm = make_arm(emulator)
    with arm:
        arm.command_positions(np.zeros(6), tau_ff=np.full(6, 1e4))
        assert wait_for(lambda: arm.stats()["torque_clamped"] > 5, 1.0)
        cmd = emulator.command()
        np.testing.assert_allclose(cmd.tau_ff, effort)
        arm.command_positions(np.zeros(6), tau_ff=np.full(6, -1e4))
        assert wait_for(lambda: np.allclose(emulator.command().tau_ff, -effort), 1.0), emulator.command().tau_ff
    assert arm.state().fault is None


def test_model_gives_limits_gains_and_payload():
    """One source: the allegro_z1 model holds the z1.md limits, the vendor LOWCMD gains and
    the hand the controller must be told about (the spec's hand link masses, 0.955 kg)."""
    from dexdrake.hardware.z1_model import z1_model

    m = z1_model()
    np.testing.assert_allclose(m.limits.effort, [30, 60, 30, 30, 30, 30])
    np.testing.assert_allclose(m.limits.velocity, math.pi)
    np.testing.assert_allclose(m.limits.kp, [20, 30, 30, 20, 15, 10])
    np.testing.assert_allclose(m.limits.kd, 2000)
    hand = 0.4154 + 3 * (0.0119 + 0.065 + 0.0355 + 0.0096 + 0.0168) + (0.0176 + 0.0119 + 0.038 + 0.0388 + 0.0168)
    assert m.payload_kg == pytest.approx(hand, abs=1e-6)
    # gravity: nothing to hold about the vertical joint1; joint3 holds the forearm + hand
    g = m.gravity(TARGET)
    assert g[0] == pytest.approx(0.0, abs=1e-9) and abs(g[2]) > 5


@pytest.mark.parametrize("kw, message", [
    ({"kp": (21, 30, 30, 20, 15, 10)}, r"kp\[0\] = 21 exceeds the LOWCMD gain 20 of joint1"),
    ({"kd": (2000,) * 5 + (2500,)}, r"kd\[5\] = 2500 exceeds"),
    ({"max_velocity": 1e9}, r"max_velocity 1e\+09 rad/s must be in \(0, 3.14159\]"),
    ({"lower": LOWER - 0.1, "upper": UPPER}, "reach outside the model"),
    ({"lower": LOWER, "upper": UPPER + 0.1}, "reach outside the model"),
    ({"max_velocity": math.pi + 0.1}, r"max_velocity 3.24159 rad/s must be in"),
    ({"max_velocity": 0.0}, r"max_velocity 0 rad/s must be in"),
    ({"kd": (-1,) * 6}, r"Z1 kd must be >= 0"),
    ({"lower": LOWER[:5]}, r"Z1 lower: need 6 finite values"),
    ({"upper": UPPER[:5]}, r"Z1 upper: need 6 finite values"),
    ({"kp": ("a",) * 6}, "Z1 kp: need 6 numbers"),
    ({"kd": (2000,) * 5}, r"Z1 kd: need 6 finite values"),
    ({"kp": (-1, 30, 30, 20, 15, 10)}, r"Z1 kp must be >= 0"),
    ({"watchdog_timeout_s": 0.0}, "watchdog_timeout_s must be > 0"),
    ({"command_period_s": 0.0}, "command_period_s must be > 0"),
])
def test_config_beyond_the_model_limits_is_refused(kw, message):
    with pytest.raises(HardwareError, match=message):
        Z1Arm(Z1Config(local_port=0, **kw))


def test_config_at_the_model_limits_and_zero_gains_is_accepted():
    arm = Z1Arm(Z1Config(local_port=0, kp=(0,) * 6, kd=(0,) * 6, max_velocity=math.pi, lower=LOWER, upper=UPPER))
    np.testing.assert_array_equal(arm.kp, 0.0)
    assert arm.settings.max_velocity == math.pi
    np.testing.assert_array_equal(arm.settings.upper, UPPER)
    np.testing.assert_array_equal(arm.limits.upper, UPPER - 0.02)  # targets: the default margin inside
    with pytest.raises(HardwareError, match="Z1: not started"):
        arm.local_port


def test_the_injected_clock_drives_the_loop_watchdog_and_time_stamps(emulator):
    """A clock 1000 s ahead of time.monotonic(): the watchdog and the state's time stamp use
    it too (a watchdog on another clock would trip at once)."""
    arm = Z1Arm(Z1Config(local_port=emulator.config.client_port, controller_port=emulator.port, lower=LOWER, upper=UPPER,
                         watchdog_timeout_s=0.2), clock=lambda: time.monotonic() + 1000.0)
    with arm:
        time.sleep(0.3)
        st = arm.state()
        assert st.fault is None and emulator.fsm == ArmFSMState.LOWCMD
        assert abs(st.t - (time.monotonic() + 1000.0)) < 0.1


def test_non_numeric_target_raises_the_drivers_error(emulator):
    arm = make_arm(emulator)
    with arm:
        with pytest.raises(HardwareError, match="numbers"):
            arm.command_positions(["up"] * 6)


def test_spontaneous_passive_is_a_fault_never_re_armed(emulator):
    """specs/z1.md: PASSIVE reported while the client streams its mode means something outside
    changed the arm's state: a fault; the client keeps commanding PASSIVE, never the mode."""
    arm = make_arm(emulator)
    with arm:
        assert wait_for(lambda: emulator.fsm == ArmFSMState.LOWCMD, 1.0)
        time.sleep(0.1)  # beyond MODE_SETTLE_TICKS of requesting the mode: no PASSIVE of the client's still acts
        emulator.force_passive(0.3)
        assert wait_for(lambda: arm.state().fault is not None, 1.0)
        assert arm.state().fault == "controller left LOWCMD for PASSIVE on its own"
        n = len(emulator.log)
        time.sleep(0.5)  # the forced PASSIVE is over: still PASSIVE, nothing asked otherwise
        assert emulator.fsm == ArmFSMState.PASSIVE
        assert all(c.state == ArmFSMState.PASSIVE for c in emulator.commands(n))


@pytest.mark.parametrize("inject, fault", [
    (lambda emu: setattr(emu, "motor_temperature_c", 71), "joint1 motor temperature 71 C (limit 70 C)"),
    (lambda emu: setattr(emu, "motor_temperature_c", -60), "joint1 motor temperature -60 C: a broken sensor"),
])
def test_motor_temperature_trips(emulator, inject, fault):
    arm = make_arm(emulator)
    with arm:
        inject(emulator)
        assert wait_for(lambda: arm.state().fault is not None, 1.0)
        assert arm.state().fault == fault
        assert wait_for(lambda: emulator.fsm == ArmFSMState.PASSIVE, 1.0)


def test_a_joint_reported_beyond_its_velocity_limit_trips():
    """The controller reports each joint's velocity: beyond pi rad/s (the model) + 50 % trips."""

    class Spinning:
        def __init__(self):
            self.w = 0.0

        def step(self, command, dt):
            return np.full(6, 0.5) * [1, 1, -1, 0, 0, 0], np.r_[self.w, np.zeros(5)], np.zeros(6)

    spin = Spinning()
    emu = Z1Emulator(Z1EmulatorConfig(port=0, client_port=free_udp_port(), lower=LOWER, upper=UPPER),
                     dynamics=spin)
    emu.start()
    try:
        arm = make_arm(emu)
        with arm:
            spin.w = 1.4 * math.pi
            time.sleep(0.2)
            assert arm.state().fault is None
            spin.w = -1.6 * math.pi
            assert wait_for(lambda: arm.state().fault is not None, 1.0)
            assert arm.state().fault == "joint1 reported at -5.03 rad/s (limit 3.14159 rad/s)"
    finally:
        emu.stop()


def test_a_storm_of_ctrl_c_never_aborts_the_safe_stop(sigint_storm):
    """SIGINT 200 times ~1 ms apart while moving: one KeyboardInterrupt, and the stop runs
    to its end: a hold at the measured position (zero velocity) first, nothing else of the
    mode after it, then PASSIVE; the socket closed."""
    emu = quiet_emulator()
    arm = make_arm(emu)
    try:
        with pytest.raises(KeyboardInterrupt):
            with arm:
                arm.command_positions(UPPER)  # 1.3 s of ramp at 2 rad/s: every command moving
                time.sleep(0.2)
                n = len(emu.log)
                sigint_storm.start()
                time.sleep(5.0)
        sigint_storm.join()
        assert not arm.running
        assert wait_for(lambda: emu.fsm == ArmFSMState.PASSIVE, 1.0)
        after = emu.commands(n)
        hold = next(i for i, c in enumerate(after) if c.state == ArmFSMState.LOWCMD
                    and all(j.W == 0.0 for j in c.joints))
        assert after[hold + 1:] and all(c.state == ArmFSMState.PASSIVE for c in after[hold + 1:])
        with pytest.raises(HardwareError, match="Z1: not started"):
            arm.local_port
    finally:
        emu.stop()


def _lowcmd_after(emu: Z1Emulator, n: int) -> list[SendCmd]:
    """The LOWCMD commands the emulator obeyed after its first `n` logged commands."""
    return [c for c in emu.commands(n) if c.state == ArmFSMState.LOWCMD]


def test_a_reset_before_the_controller_is_heard_again_re_arms_at_the_measured_position(emulator):
    """The last state heard before a silence shows the arm at its old target; it sagged in
    PASSIVE since. reset_fault() while the controller is still silent: the client commands
    PASSIVE until it hears a state, then re-enters LOWCMD holding that measured position
    with no velocity and no torque but gravity's (the old set-point and feed-forward
    are gone), and no overspeed follows."""
    arm = make_arm(emulator, watchdog_timeout_s=2.0)  # outlasts the test's steps while stalled
    with arm:
        arm.command_positions(TARGET, tau_ff=np.full(6, 0.3))
        assert wait_for(lambda: np.max(np.abs(emulator.q - TARGET)) < 0.05, 20.0)
        emulator.stall(30.0)
        assert wait_for(lambda: arm.state().fault is not None, 5.0)
        assert wait_for(lambda: np.max(np.abs(emulator.q - TARGET)) > 0.3, 3.0)  # sagged, PASSIVE
        time.sleep(0.3)
        n = len(emulator.log)
        arm.reset_fault()
        assert wait_for(lambda: arm.state().fault is None, 5.0)  # reset done, nothing heard yet
        time.sleep(0.02)
        assert not _lowcmd_after(emulator, n)
        q_sag = emulator.q
        emulator.stall(0)
        assert wait_for(lambda: emulator.fsm == ArmFSMState.LOWCMD, 5.0), arm.state().fault
        first = _lowcmd_after(emulator, n)[0].joints[:6]
        q_first = np.array([j.Pos for j in first])
        np.testing.assert_allclose(q_first, np.clip(q_sag, LOWER + 0.02, UPPER - 0.02), atol=0.02)
        np.testing.assert_allclose([j.W for j in first], 0.0)
        np.testing.assert_allclose([j.T for j in first], arm.model.gravity(q_first), atol=1e-4)
        time.sleep(0.3)
        assert arm.state().fault is None and emulator.fsm == ArmFSMState.LOWCMD
        np.testing.assert_allclose(emulator.q, q_sag, atol=0.05)


def test_the_target_follows_the_arm_until_the_controller_takes_the_mode_again(emulator):
    """After reset_fault() the controller refuses LOWCMD for a while and the arm keeps
    sagging: the client re-arms holding where the arm is when LOWCMD is entered, not where
    it was at the reset."""
    arm = make_arm(emulator)
    with arm:
        arm.command_positions(TARGET)
        assert wait_for(lambda: np.max(np.abs(emulator.q - TARGET)) < 0.05, 20.0)
        emulator.motor_temperature_c = 71
        assert wait_for(lambda: arm.state().fault is not None, 1.0)
        emulator.motor_temperature_c = 25
        time.sleep(0.2)  # no reply with the old temperature is left on its way
        emulator.force_passive(1.0)
        n = len(emulator.log)
        arm.reset_fault()
        assert wait_for(lambda: emulator.fsm == ArmFSMState.LOWCMD, 10.0), arm.state().fault
        assert np.max(np.abs(emulator.q - TARGET)) > 0.3  # it sagged while refused
        first = np.array([j.Pos for j in _lowcmd_after(emulator, n)[-1].joints[:6]])
        time.sleep(0.3)
        assert arm.state().fault is None
        np.testing.assert_allclose(arm.state().q_target, first, atol=0.05)
        assert np.max(np.abs(emulator.q - TARGET)) > 0.3
