"""The emulated Z1 controller driven tick by tick (`open()` / `poll(now)`, an injected clock):
its torque law, joint dynamics, state machine timings, replies and fault injection."""

import gc
import socket

import numpy as np
import pytest

from dexdrake.hardware.safety import HardwareError
from dexdrake.hardware.z1_emulator import (
    ArmCommand,
    SimpleArmDynamics,
    Z1Emulator,
    Z1EmulatorConfig,
    flange_posture,
)
from dexdrake.hardware.z1_model import KD_SCALE, KP_SCALE, z1_model
from dexdrake.hardware.z1_udp import ArmFSMState, JointCmd, PacketError, RecvState, SendCmd

from test_z1_udp import LOWER, UPPER  # z1.md's limits, one copy

EFFORT = np.array([30.0, 60.0, 30.0, 30.0, 30.0, 30.0])


def command(fsm=ArmFSMState.LOWCMD, q_d=0.0, dq_d=0.0, tau_ff=0.0, kp=0.0, kd=0.0) -> ArmCommand:
    return ArmCommand(fsm, *(np.full(6, float(v)) for v in (q_d, dq_d, tau_ff, kp, kd)))


def test_torque_law_each_term_and_the_effort_clip():
    q, dq = np.full(6, 0.1), np.full(6, -0.5)
    tau = command(q_d=0.3, dq_d=0.5, tau_ff=0.25, kp=2.0, kd=40.0).torque(q, dq, 5.0, EFFORT)
    np.testing.assert_allclose(tau, 2.0 * KP_SCALE * 0.2 + 40.0 * KD_SCALE * 1.0 + 0.25)
    assert (KP_SCALE, KD_SCALE) == (25.6, 0.0128)
    big = command(q_d=3.0, kp=20.0).torque(np.zeros(6), np.zeros(6), 5.0, EFFORT)
    np.testing.assert_allclose(big, EFFORT)
    np.testing.assert_allclose(command(q_d=-3.0, kp=20.0).torque(np.zeros(6), np.zeros(6), 5.0, EFFORT), -EFFORT)
    # PASSIVE: damping of the measured velocity only, whatever the command says
    passive = command(ArmFSMState.PASSIVE, q_d=3.0, tau_ff=7.0, kp=20.0)
    np.testing.assert_allclose(passive.torque(q, dq, 5.0, EFFORT), 2.5)
    np.testing.assert_allclose(passive.torque(q, np.full(6, 100.0), 5.0, EFFORT), -EFFORT)


def test_dynamics_integrate_torque_gravity_and_damping():
    """From rest, one 10 ms step of a constant torque: q moves by about a*dt^2/2 with
    a = (tau - gravity) / inertia, in the torque's direction; damping slows a moving joint."""
    inertia = np.array([0.15, 0.3, 0.15, 0.05, 0.03, 0.02])
    load = np.array([0.0, 1.0, -1.0, 0.5, 0.0, 0.0])
    dyn = SimpleArmDynamics(np.zeros(6) + 0.5 * (LOWER + UPPER), LOWER, UPPER, inertia, damping=0.0,
                            passive_damping=5.0, effort=EFFORT, physics_dt_s=0.0005, gravity=lambda q: load)
    q0 = dyn.q.copy()
    q, dq, tau = dyn.step(command(tau_ff=2.0), 0.01)
    a = (2.0 - load) / inertia
    np.testing.assert_allclose(tau, 2.0)
    np.testing.assert_allclose(dq, a * 0.01, rtol=1e-9)
    # semi-implicit Euler over 20 sub-steps: a dt^2 (n + 1) / (2 n)
    np.testing.assert_allclose(q - q0, a * 0.01**2 * 21 / 40, rtol=1e-9)
    damped = SimpleArmDynamics(q0, LOWER, UPPER, inertia, damping=0.5, passive_damping=5.0, effort=EFFORT)
    damped.dq = np.ones(6)
    _, dq, _ = damped.step(command(), 0.001)  # two sub-steps of dq *= 1 - h b / I
    np.testing.assert_allclose(dq, (1 - 0.0005 * 0.5 / inertia) ** 2, rtol=1e-12)


def test_dynamics_stop_at_the_joint_limits():
    dyn = SimpleArmDynamics(np.zeros(6), LOWER, UPPER, [0.05] * 6, 0.5, 5.0, EFFORT)
    for sign, stop in ((1.0, UPPER), (-1.0, LOWER)):
        for _ in range(200):
            q, dq, _ = dyn.step(command(tau_ff=sign * 30.0), 0.01)
        np.testing.assert_allclose(q, stop)
        np.testing.assert_array_equal(dq, 0.0)  # no velocity into the stop
    q0 = SimpleArmDynamics(np.full(6, 9.0), LOWER, UPPER, [0.05] * 6, 0.5, 5.0, EFFORT).q
    np.testing.assert_allclose(q0, UPPER)


def test_flange_posture_at_zero_matches_spec_origins():
    rx, ry, rz, x, y, z = flange_posture(np.zeros(6))
    assert (rx, ry, rz) == pytest.approx((0, 0, 0))
    assert (x, y, z) == pytest.approx((-0.35 + 0.218 + 0.07 + 0.0492, 0.0, 0.0585 + 0.045 + 0.057))


def test_flange_posture_matches_the_model_file_away_from_zero():
    """Roll-pitch-yaw and position of link06 in link00 agree with Drake's kinematics of the
    allegro_z1 model at random joint angles (at zero every rotation is the identity)."""
    from pydrake.math import RollPitchYaw
    from pydrake.multibody.parsing import Parser
    from pydrake.multibody.plant import MultibodyPlant

    from dexdrake.hands.description import load_hand

    plant = MultibodyPlant(0.0)
    (robot,) = Parser(plant).AddModels(str(load_hand("allegro_z1").model_path))
    plant.Finalize()
    ctx = plant.CreateDefaultContext()
    joints = [plant.GetJointByName(f"joint{i}", robot) for i in range(1, 7)]
    base, flange = plant.GetFrameByName("link00", robot), plant.GetFrameByName("link06", robot)
    rng = np.random.default_rng(4)
    for _ in range(5):
        q = rng.uniform(LOWER, UPPER)
        for joint, angle in zip(joints, q):
            joint.set_angle(ctx, angle)
        X = plant.CalcRelativeTransform(ctx, base, flange)
        rpy = RollPitchYaw(X.rotation()).vector()
        posture = flange_posture(q)
        np.testing.assert_allclose(posture[3:], X.translation(), atol=1e-9)
        np.testing.assert_allclose(posture[:3], rpy, atol=1e-9)


class Link:
    """An emulator stepped by hand on a fake clock, and a client socket talking to it."""

    def __init__(self, **kw):
        self.now = 0.0
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.bind(("127.0.0.1", 0))  # the client's port, given to the emulator
        self.sock.settimeout(0.5)
        kw.setdefault("port", 0)
        self.emu = Z1Emulator(Z1EmulatorConfig(lower=LOWER, upper=UPPER, client_port=self.sock.getsockname()[1],
                                               **kw), clock=lambda: self.now)
        self.emu.open()

    def send(self, cmd: SendCmd, at: float, reply: bool = True) -> RecvState | None:
        self.now = at
        self.sock.sendto(cmd.pack(), ("127.0.0.1", self.emu.port))
        self.emu.poll(at, timeout=0.5)
        if not reply:
            return None
        return RecvState.unpack(self.sock.recv(4096))

    def close(self) -> None:
        self.sock.close()
        self.emu.close()


@pytest.fixture
def link():
    link = Link()
    yield link
    link.close()


def test_silence_changes_nothing_the_last_command_goes_on(link):
    """specs/z1.md documents no command timeout: the controller keeps executing the last
    command, whatever the silence (the less convenient assumption for the client)."""
    for mode in (ArmFSMState.LOWCMD, ArmFSMState.JOINTCTRL):
        assert link.send(SendCmd(mode), at=link.now + 1.0).state == mode
        before = link.emu.command()
        for k in range(1, 40):
            link.emu.poll(link.now + 0.05 * k)
        assert link.emu.fsm == mode and link.emu.command().fsm == before.fsm
        np.testing.assert_array_equal(link.emu.command().q_d, before.q_d)
        link.send(SendCmd(ArmFSMState.PASSIVE), at=link.now + 3.0)


def test_replies_go_to_the_client_port_only():
    """The controller sends to the client's fixed port, never to a command's source."""
    link = Link()
    stranger = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    stranger.bind(("127.0.0.1", 0))
    stranger.settimeout(0.1)
    try:
        stranger.sendto(SendCmd(ArmFSMState.PASSIVE).pack(), ("127.0.0.1", link.emu.port))
        link.emu.poll(1.0, timeout=0.5)
        assert link.emu.commands_received == 1
        with pytest.raises(socket.timeout):
            stranger.recv(4096)
        assert RecvState.unpack(link.sock.recv(4096)).state == ArmFSMState.PASSIVE
    finally:
        stranger.close()
        link.close()


def test_entering_jointctrl_holds_the_current_position_with_the_default_gains():
    link = Link(q0=[0.2, 0.5, -0.4, 0.1, 0.0, 0.3])
    try:
        model = z1_model()
        link.send(SendCmd(ArmFSMState.JOINTCTRL, track=False), at=0.001)
        cmd = link.emu.command()
        assert cmd.fsm == ArmFSMState.JOINTCTRL
        np.testing.assert_allclose(cmd.q_d, link.emu.q)
        np.testing.assert_allclose(cmd.q_d, [0.2, 0.5, -0.4, 0.1, 0.0, 0.3], atol=1e-3)
        np.testing.assert_array_equal(cmd.dq_d, 0.0)
        np.testing.assert_allclose(cmd.kp, model.limits.kp)
        np.testing.assert_allclose(cmd.kd, model.limits.kd)
        np.testing.assert_allclose(cmd.tau_ff, model.gravity(cmd.q_d))  # its own gravity compensation
        # LOWCMD: the client's terms replace everything as soon as they arrive
        link.send(SendCmd(ArmFSMState.PASSIVE), at=0.002)
        joints = (JointCmd(T=1.0, W=0.5, Pos=0.3, K_P=2.0, K_W=30.0),) * 6 + (JointCmd(),)
        link.send(SendCmd(ArmFSMState.LOWCMD, joints), at=link.now + 0.001)
        cmd = link.emu.command()
        for got, want in ((cmd.q_d, 0.3), (cmd.dq_d, 0.5), (cmd.tau_ff, 1.0), (cmd.kp, 2.0), (cmd.kd, 30.0)):
            np.testing.assert_allclose(got, want)
    finally:
        link.close()


def test_jointctrl_targets_are_clipped_and_compensated(link):
    link.send(SendCmd(ArmFSMState.JOINTCTRL), at=1.0)
    joints = tuple(JointCmd(Pos=p, W=0.25) for p in (9.0, -9.0, 9.0, -9.0, 0.5, 0.0)) + (JointCmd(),)
    link.send(SendCmd(ArmFSMState.JOINTCTRL, joints, track=True), at=1.001)
    cmd = link.emu.command()
    np.testing.assert_allclose(cmd.q_d, np.clip([9.0, -9.0, 9.0, -9.0, 0.5, 0.0], LOWER, UPPER))
    np.testing.assert_allclose(cmd.dq_d, 0.25)
    np.testing.assert_allclose(cmd.tau_ff, z1_model().gravity(cmd.q_d))


def test_weightless_config_and_gravity_direction():
    """With gravity the PASSIVE arm falls (joint2 toward positive angles, the
    forearm's weight); weightless it stays put, and JOINTCTRL adds no compensation."""
    fell = {}
    for gravity in (True, False):
        link = Link(gravity=gravity, q0=[0.0, 1.0, -1.0, 0.0, 0.0, 0.0])
        try:
            q0 = link.emu.q
            for k in range(1, 21):
                link.emu.poll(0.01 * k)
            fell[gravity] = link.emu.q - q0
            if not gravity:
                link.send(SendCmd(ArmFSMState.JOINTCTRL), at=1.0)
                np.testing.assert_array_equal(link.emu.command().tau_ff, 0.0)
        finally:
            link.close()
    np.testing.assert_array_equal(fell[False], 0.0)
    g = z1_model().gravity(np.array([0.0, 1.0, -1.0, 0.0, 0.0, 0.0]))
    assert np.all(np.sign(fell[True][1:3]) == -np.sign(g[1:3])) and np.min(np.abs(fell[True][1:3])) > 1e-3


def test_a_tick_steps_at_most_50_ms():
    link = Link()
    try:
        link.send(SendCmd(ArmFSMState.LOWCMD, (JointCmd(T=2.0),) * 6 + (JointCmd(),)), at=0.0)
        link.emu.poll(10.0)  # a 10 s stall of the caller: one 50 ms step, not 10 s of motion
        dyn = SimpleArmDynamics(np.zeros(6), LOWER, UPPER, Z1EmulatorConfig.inertia, 0.5, 5.0, EFFORT,
                                gravity=z1_model().gravity)
        q, _, _ = dyn.step(command(tau_ff=2.0), 0.05)
        np.testing.assert_allclose(link.emu.q, q, atol=1e-9)
        assert np.max(np.abs(q)) > 0.01
    finally:
        link.close()


def test_a_stall_keeps_obeying():
    link = Link()
    listener = link.sock
    try:
        link.send(SendCmd(ArmFSMState.LOWCMD), at=1.0, reply=False)
        assert RecvState.unpack(listener.recv(4096)).state == ArmFSMState.LOWCMD
        link.emu.stall(0.5)
        assert link.emu.stall_until == pytest.approx(1.5)
        link.send(SendCmd(ArmFSMState.PASSIVE), at=1.2, reply=False)
        assert link.emu.fsm == ArmFSMState.PASSIVE and link.emu.commands_received == 2
        listener.settimeout(0.1)
        with pytest.raises(socket.timeout):
            listener.recv(4096)
        link.send(SendCmd(ArmFSMState.PASSIVE), at=1.6, reply=False)
        assert RecvState.unpack(listener.recv(4096)).state == ArmFSMState.PASSIVE
    finally:
        link.close()


def test_the_command_log_gives_the_garbage_collector_nothing_to_walk(link):
    """A full collection stops the emulator while it walks every tracked object: however
    many commands the log keeps, it adds none (they are decoded when asked for)."""
    cmd = SendCmd(ArmFSMState.LOWCMD, (JointCmd(1.0, 2.0, 0.5, 20.0, 2000.0),) * 7)
    link.send(cmd, at=0.001)
    gc.collect()
    tracked = len(gc.get_objects())
    for k in range(2, 502):
        link.send(cmd, at=0.001 * k)
    gc.collect()
    assert len(gc.get_objects()) - tracked < 100
    assert len(link.emu.log) == 501 and link.emu.commands(500) == [cmd]


def test_fault_injection_corrupts_replies_and_reports_motor_errors(link):
    link.emu.motor_error = (3, 0x04)
    st = link.send(SendCmd(ArmFSMState.PASSIVE), at=1.0)
    assert [j.motors[0].error for j in st.joints] == [0, 0, 0, 0x04, 0, 0, 0]
    assert all(j.motors[1].error == 0 for j in st.joints)
    link.emu.corrupt_replies = True
    kinds = set()
    for k in range(30):
        link.send(SendCmd(ArmFSMState.PASSIVE), at=1.0 + 0.001 * k, reply=False)
        data = link.sock.recv(4096)
        try:
            RecvState.unpack(data)
        except PacketError as err:
            kinds.add(err.kind)
    assert kinds == {"size", "enum", "nonfinite"}


def test_replies_report_the_joints_in_the_arm_slots_only():
    link = Link(q0=[0.3, 0.6, -0.9, 0.2, -0.1, 0.4])
    try:
        st = link.send(SendCmd(ArmFSMState.PASSIVE), at=1.0)
        np.testing.assert_allclose([j.Pos for j in st.joints[:6]], [0.3, 0.6, -0.9, 0.2, -0.1, 0.4], atol=1e-3)
        assert st.joints[6].Pos == 0.0 and st.joints[6].T == 0.0
    finally:
        link.close()


def test_socket_life_cycle_errors():
    emu = Z1Emulator(Z1EmulatorConfig(port=0))
    with pytest.raises(HardwareError, match="Z1 emulator: not started"):
        emu.port
    with pytest.raises(HardwareError, match="^Z1 emulator: not open$"):
        emu.poll(0.0)
    emu.open()
    try:
        with pytest.raises(HardwareError, match="^Z1 emulator: already open$"):
            emu.open()
        with pytest.raises(HardwareError, match=f"cannot bind 127.0.0.1:{emu.port}"):
            Z1Emulator(Z1EmulatorConfig(port=emu.port)).open()
    finally:
        emu.close()
    with pytest.raises(HardwareError, match="q0 needs 6 values"):
        Z1Emulator(Z1EmulatorConfig(port=0, q0=[0.0] * 5))


def test_thread_start_stop_and_context_manager():
    """In its own thread: answers while running; stop() joins it and closes the socket."""
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sock.bind(("127.0.0.1", 0))
    with Z1Emulator(Z1EmulatorConfig(port=0, client_port=sock.getsockname()[1], lower=LOWER, upper=UPPER)) as emu:
        assert emu._thread is not None and emu._thread.is_alive()
        sock.settimeout(1.0)
        try:
            sock.sendto(SendCmd(ArmFSMState.LOWCMD).pack(), ("127.0.0.1", emu.port))
            assert RecvState.unpack(sock.recv(4096)).state == ArmFSMState.LOWCMD
        finally:
            sock.close()
        thread = emu._thread
    assert not thread.is_alive() and emu._thread is None
    with pytest.raises(HardwareError, match="not started"):
        emu.port
    emu.start()  # a stopped emulator starts again
    try:
        assert emu._thread.is_alive()
    finally:
        emu.stop()


def test_limits_q0_and_state_machine_counts():
    assert Z1Emulator(Z1EmulatorConfig(port=0)).upper == pytest.approx(UPPER, abs=1e-4)  # the model's
    emu = Z1Emulator(Z1EmulatorConfig(port=0, lower=LOWER + 0.1, upper=UPPER - 0.1, q0=[9.0] * 6))
    np.testing.assert_allclose(emu.lower, LOWER + 0.1)
    np.testing.assert_allclose(emu.q, UPPER - 0.1)  # q0 clipped into the limits
    np.testing.assert_allclose(Z1Emulator(Z1EmulatorConfig(port=0, lower=LOWER, upper=UPPER, q0=[-9.0] * 6)).q,
                               LOWER)
    link = Link()
    try:
        assert link.emu.fsm == ArmFSMState.PASSIVE
        link.send(SendCmd(ArmFSMState.JOINTCTRL), at=1.0)
        for _ in range(2):
            assert link.send(SendCmd(ArmFSMState.LOWCMD), at=1.001).state == ArmFSMState.JOINTCTRL
        assert link.emu.rejected_transitions == {"JOINTCTRL->LOWCMD": 2}
        # one poll drains everything queued: two bad sizes, two bad heads, then a valid command
        for data in (b"\x00" * 5, b"\x00" * 5) + (SendCmd(ArmFSMState.PASSIVE, head=(0xFE, 0xEF)).pack(),) * 2:
            link.sock.sendto(data, ("127.0.0.1", link.emu.port))
        n = link.emu.commands_received
        link.send(SendCmd(ArmFSMState.JOINTCTRL), at=1.002)
        assert link.emu.packet_errors == {"size": 2, "head": 2} and link.emu.commands_received == n + 1
        st = link.send(SendCmd(ArmFSMState.PASSIVE), at=1.003)
        assert all(j.Acc == 0.0 for j in st.joints)
        np.testing.assert_allclose(st.posture, flange_posture([j.Pos for j in st.joints[:6]]), atol=1e-5)
    finally:
        link.close()


def test_one_sub_step_when_the_tick_is_shorter_than_the_physics_step():
    mid = 0.5 * (LOWER + UPPER)
    dyn = SimpleArmDynamics(mid, LOWER, UPPER, [0.1] * 6, 0.0, 5.0, EFFORT, physics_dt_s=0.001)
    q, dq, _ = dyn.step(command(tau_ff=1.0), 0.0005)
    np.testing.assert_allclose(dq, 10.0 * 0.0005)
    np.testing.assert_allclose(q - mid, 10.0 * 0.0005**2)  # one semi-implicit Euler step
