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
)
from waiting import wait_for

# z1.md, current limits
LOWER = np.array([-2.6180, 0.0, -2.8798, -1.5184, -1.3439, -2.7925])
UPPER = np.array([2.6180, 2.9671, 0.0, 1.5184, 1.3439, 2.7925])
TARGET = np.array([0.5, 1.0, -1.0, 0.3, -0.3, 0.5])


@pytest.fixture
def emulator():
    emu = Z1Emulator(Z1EmulatorConfig(port=0, lower=LOWER, upper=UPPER))
    emu.start()
    yield emu
    emu.stop()


def make_arm(emu: Z1Emulator, **kw) -> Z1Arm:
    # a watchdog generous enough for a loaded 2-core CI machine; stalls below are longer
    kw.setdefault("watchdog_timeout_s", 0.2)
    return Z1Arm(Z1Config(local_port=0, controller_port=emu.port, lower=LOWER, upper=UPPER, **kw))


class RawClient:
    """A bare UDP socket speaking SendCmd/RecvState, for FSM tests."""

    def __init__(self, port: int):
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.bind(("127.0.0.1", 0))
        self.sock.settimeout(0.5)
        self.port = port

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
    st = RecvState(ArmFSMState.JOINTCTRL, (js,) * 7, (0.1, 0.2, 0.3, 0.4, 0.5, 0.75))
    raw = st.pack()
    assert struct.unpack_from("<6d", raw, 208 - 48) == st.posture
    assert RecvState.unpack(raw) == st


@pytest.mark.parametrize("make, kind", [
    (lambda: SendCmd.unpack(b"\x00" * 146), "size"),
    (lambda: RecvState.unpack(b"\x00" * 209), "size"),
    (lambda: SendCmd.unpack(b"\x00\x00" + (17).to_bytes(4, "little") + b"\x00" * 141), "enum"),
    (lambda: RecvState.unpack(b"\x00\x00" + (2**31 - 1).to_bytes(4, "little") + b"\x00" * 202), "enum"),
    (lambda: SendCmd.unpack(b"\x00\x00" + (1).to_bytes(4, "little") + b"\x02" + b"\x00" * 140), "range"),
    (lambda: SendCmd.unpack(b"\x00\x00" + (1).to_bytes(4, "little") + b"\x00"
                            + struct.pack("<5f", math.nan, 0, 0, 0, 0) + b"\x00" * 120), "nonfinite"),
    (lambda: JointCmd(Pos=math.inf).pack(), "nonfinite"),
    (lambda: JointState(motors=(MotorState(temperature=300), MotorState())).pack(), "range"),
])
def test_validation_errors(make, kind):
    with pytest.raises(PacketError) as err:
        make()
    assert err.value.kind == kind


def test_flange_posture_at_zero_matches_spec_origins():
    rx, ry, rz, x, y, z = flange_posture(np.zeros(6))
    assert (rx, ry, rz) == pytest.approx((0, 0, 0))
    assert (x, y, z) == pytest.approx((-0.35 + 0.218 + 0.07 + 0.0492, 0.0, 0.0585 + 0.045 + 0.057))


def test_default_limits_from_description():
    lo, hi = default_joint_limits()
    np.testing.assert_allclose(lo, LOWER, atol=1e-4)
    np.testing.assert_allclose(hi, UPPER, atol=1e-4)


# ------------------------------------------------------------------ emulator FSM
def test_emulator_fsm_rules(emulator):
    c = RawClient(emulator.port)
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
        # silence in LOWCMD drops the arm to PASSIVE
        assert wait_for(lambda: emulator.fsm == ArmFSMState.PASSIVE, 1.0)
        # garbage is counted, not answered
        c.sock.sendto(b"\x01\x02\x03", ("127.0.0.1", emulator.port))
        assert wait_for(lambda: emulator.packet_errors["size"] == 1, 1.0)
    finally:
        c.close()


def test_emulator_lowcmd_torque_law(emulator):
    """The reported torque equals kp*25.6*(q_d - q) + kd*0.0128*(dq_d - dq) + tau_ff."""
    c = RawClient(emulator.port)
    try:
        c.send(SendCmd(ArmFSMState.LOWCMD))
        q_d, kp, tau_ff = 0.001, 1.0, 0.5
        cmd = SendCmd(ArmFSMState.LOWCMD, (JointCmd(T=tau_ff, Pos=q_d, K_P=kp),) * 6 + (JointCmd(),))
        st = c.send(cmd)
        st = c.send(cmd)
        j = st.joints[0]
        assert j.T == pytest.approx(kp * 25.6 * (q_d - j.Pos) + tau_ff, abs=0.05)
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
    emu = Z1Emulator(Z1EmulatorConfig(port=0, lower=LOWER, upper=UPPER), dynamics=dynamics)
    emu.start()
    c = RawClient(emu.port)
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


def test_velocity_limit_on_targets(emulator):
    arm = make_arm(emulator)
    with arm:
        arm.command_positions(UPPER)
        time.sleep(0.1)
        # pi rad/s for about 0.1 s: well short of the 2.6 rad commanded on joint 1
        assert np.max(np.abs(arm.state().q_target)) < 0.7


def test_nan_and_out_of_range_targets(emulator):
    arm = make_arm(emulator)
    with arm:
        np.testing.assert_allclose(arm.command_positions(TARGET), TARGET)
        np.testing.assert_allclose(arm.command_positions([math.nan] * 6), TARGET)
        np.testing.assert_allclose(arm.command_positions(np.full(6, 9.0)), UPPER)
        assert arm.stats()["rejected_commands"] == 1 and arm.stats()["clamped_commands"] == 1
        with pytest.raises(HardwareError):
            arm.command_positions(np.zeros(5))
        assert wait_for(lambda: np.max(np.abs(emulator.q - UPPER)) < 0.01, 4.0)


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
        assert "joint3" in arm.state().fault
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


def test_start_without_controller_fails_cleanly():
    free = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    free.bind(("127.0.0.1", 0))
    port = free.getsockname()[1]
    free.close()
    arm = Z1Arm(Z1Config(local_port=0, controller_port=port, lower=LOWER, upper=UPPER,
                          mode_timeout_s=0.3))
    with pytest.raises(HardwareError, match="start failed"):
        arm.start()
    assert not arm.running


def test_official_backend_explains_missing_module():
    with pytest.raises(HardwareError, match="unitree_arm_interface"):
        OfficialZ1(lower=LOWER, upper=UPPER)
