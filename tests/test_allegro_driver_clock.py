"""The Allegro driver's loop, one frame at a time on a fake clock (no loop thread): the PD
law, the position filter and the PWM limits to the count, and the faults it reports."""

import uuid

import can
import numpy as np
import pytest

from dexdrake.hands import allegro_units as units
from dexdrake.hardware.allegro_can import (
    AllegroConfig,
    AllegroHand,
    Imu,
    Info,
    Position,
    ServoOff,
    Status,
    Temperature,
    Torque,
    decode,
    encode,
)
from test_allegro_can import LOWER, UPPER  # the spec table's joint limits, bus order

PERIOD = 0.003  # s between position batches (the configured 3 ms)


class FakeClock:
    def __init__(self, t: float = 0.0):
        self.t = t

    def __call__(self) -> float:
        return self.t


@pytest.fixture
def bench():
    """(hand on a fake clock, the bus end that hears its frames, the clock); not started."""
    channel = f"allegro-clock-{uuid.uuid4().hex}"
    host = can.Bus(interface="virtual", channel=channel)
    spare = can.Bus(interface="virtual", channel=channel)
    clock = FakeClock()
    hand = AllegroHand(host, config=AllegroConfig(lower=LOWER, upper=UPPER, watchdog_timeout_s=0.2,
                                                  temperature_timeout_s=0.5, limit_margin_rad=0.0),
                       clock=clock)  # no margin: targets clamp onto the limits, as computed below
    yield hand, spare, clock
    host.shutdown()
    spare.shutdown()


def on_counts(q: np.ndarray) -> np.ndarray:
    """`q` rounded to what the encoders can report."""
    return units.counts_to_rad(units.rad_to_counts(q))


def finger(hand: AllegroHand, f: int, q: np.ndarray) -> None:
    """Finger `f`'s position frame (its 4 joints of `q`) reaching the driver."""
    hand._handle(Position(f, tuple(int(c) for c in units.rad_to_counts(q[4 * f: 4 * f + 4]))))


def positions(hand: AllegroHand, q: np.ndarray) -> None:
    """One complete batch of position frames (4 fingers) reaching the driver."""
    for f in range(4):
        finger(hand, f, q)


def frames(spare: can.BusABC) -> list:
    """Every frame the hand has sent so far."""
    out = []
    while (msg := spare.recv(0.05)) is not None:
        out.append(decode(msg))
    return out


def torques(spare: can.BusABC) -> np.ndarray:
    """The PWM of the 4 torque frames of one cycle, in bus order."""
    sent = [decode(spare.recv(1.0)) for _ in range(4)]
    assert all(isinstance(f, Torque) for f in sent), sent
    return np.concatenate([f.pwm for f in sorted(sent, key=lambda f: f.finger)]).astype(float)


def test_pd_step_is_the_control_law_to_the_count(bench):
    """First batch: hold the measured position (clamped into the limits), zero torque. Next
    batch: low-pass filtered position, its derivative, the rate-limited target and
    PWM = clip(rint(kp (q_ref - q) - kd dq), +-limit), independently computed here."""
    hand, spare, clock = bench
    st = hand.state()  # nothing heard yet
    assert np.isnan(st.t) and st.status is None and hand.info is None
    assert np.all(st.q == 0) and np.all(st.dq == 0) and np.all(np.isnan(st.temperature_c))
    q0 = on_counts(LOWER + 0.5 * (UPPER - LOWER))
    q0[0], q0[5] = on_counts(LOWER[0] - 0.1), on_counts(UPPER[5] + 0.1)  # measured beyond the limits
    clock.t = 1.0
    positions(hand, q0)
    assert np.all(torques(spare) == 0)
    st = hand.state()
    held = np.clip(q0, LOWER, UPPER)
    assert st.t == 1.0 and np.array_equal(st.q, q0) and np.all(st.dq == 0)
    np.testing.assert_array_equal(st.q_target, held)

    target = np.where(np.arange(16) % 2 == 0, UPPER, LOWER)  # half the joints up, half down
    hand.command_positions(target)
    q1 = on_counts(q0 + np.linspace(-0.002, 0.002, 16))
    clock.t = 1.0 + PERIOD
    positions(hand, q1)
    dt = clock.t - 1.0
    alpha = dt / (dt + 1 / (2 * np.pi * 80.0))  # the 80 Hz default cut-off
    q = q0 + alpha * (q1 - q0)
    dq = (q - q0) / dt
    q_ref = held + np.clip(target - held, -3.0 * dt, 3.0 * dt)  # 3 rad/s
    pwm = np.clip(np.rint(units.KP_VENDOR * (q_ref - q) - units.KD_VENDOR * dq), -units.PWM_LIMITS, units.PWM_LIMITS)
    np.testing.assert_array_equal(torques(spare), pwm)
    st = hand.state()
    np.testing.assert_allclose(st.q, q, rtol=0, atol=1e-12)
    np.testing.assert_allclose(st.dq, dq, rtol=0, atol=1e-9)
    np.testing.assert_allclose(st.q_target, q_ref, rtol=0, atol=1e-12)
    np.testing.assert_array_equal(st.tau_pwm, pwm)
    assert st.t == clock.t and st.fault is None

    # the fingers blocked where they are: the target walks away until the PWM saturates
    for _ in range(400):
        clock.t += PERIOD
        positions(hand, q1)
        pwm = torques(spare)
    st = hand.state()
    np.testing.assert_array_equal(st.q_target, target)
    expect = np.clip(np.rint(units.KP_VENDOR * (target - st.q) - units.KD_VENDOR * st.dq),
                     -units.PWM_LIMITS, units.PWM_LIMITS)
    np.testing.assert_array_equal(pwm, expect)
    assert pwm[12] == units.PWM_LIMITS[12] and pwm[1] == -units.PWM_LIMITS[1]  # both limits reached


def test_loop_faults_say_how_long_and_which_finger(bench):
    hand, spare, clock = bench
    clock.t = 0.7  # the hand was made at 0: no position frame since
    hand._iterate(clock.t)
    assert hand.state().fault == "position stream silent for 700 ms"
    assert hand.stats()["fault"] == hand.state().fault

    hand.reset_fault()
    q = on_counts(LOWER + 0.5 * (UPPER - LOWER))
    for f, t in ((2, 1.0), (0, 1.1), (1, 1.1), (3, 1.1)):  # finger 2 heard first
        clock.t = t
        hand._handle(Temperature(f, (30 + f, 31 + f, 32 + f, 33 + f)))
    hand._handle(Status(0))
    hand._handle(Imu((1, 2, 3, 4)))  # not used by the driver
    st = hand.state()
    np.testing.assert_array_equal(st.temperature_c, [30 + f + j for f in range(4) for j in range(4)])
    assert st.status == 0 and st.fault is None and hand.stats()["ignored_frames"] == 1
    for t in (1.5, 1.6):  # positions keep coming: only the temperatures time out
        clock.t = t
        positions(hand, q)
        hand._iterate(clock.t)
        if t == 1.5:
            assert hand.state().fault is None  # 0.5 s is not more than the 0.5 s timeout
    assert hand.state().fault == "finger 2 temperature not heard for 600 ms"


def test_safe_stop_is_sent_once_per_fault_and_again_after_a_reset(bench):
    hand, spare, clock = bench
    hot = Temperature(1, (90, 20, 20, 20))
    hand._handle(hot)
    hand._handle(hot)  # still hot: the fault stays latched, the stop is not repeated
    sent = frames(spare)
    assert "finger 1 joint temperature 90 C" in hand.state().fault
    assert sent == [Torque(f, (0, 0, 0, 0)) for f in range(4)] + [ServoOff()]
    hand.reset_fault()
    assert hand.state().fault is None
    hand._handle(Status(0x02))
    assert "status 0x02" in hand.state().fault
    assert frames(spare) == [Torque(f, (0, 0, 0, 0)) for f in range(4)] + [ServoOff()]


def test_a_bus_error_during_the_safe_stop_leaves_the_fault_latched(bench):
    hand, spare, clock = bench

    def broken(msg, timeout=None):
        raise can.CanOperationError("transmit buffer full")

    hand.bus.send = broken
    hand._handle(Temperature(0, (95, 20, 20, 20)))  # no exception escapes into the loop
    assert "temperature 95 C" in hand.state().fault
    assert np.all(hand.state().tau_pwm == 0)


def test_position_frames_beyond_the_limits_and_margin_are_refused(bench):
    """Within limits +- 0.3 rad a frame counts; beyond, it is refused and counted, and a
    batch is complete only with 4 accepted frames; a finger repeated is a duplicate."""
    hand, spare, clock = bench
    q = on_counts(LOWER + 0.5 * (UPPER - LOWER))
    below, above, edge = q.copy(), q.copy(), q.copy()
    below[0], above[5] = LOWER[0] - 0.32, UPPER[5] + 0.32
    edge[0], edge[5] = LOWER[0] - 0.28, UPPER[5] + 0.28  # implausible but within the margin
    finger(hand, 0, below)
    finger(hand, 1, above)
    for f in (1, 2, 3):
        finger(hand, f, edge)
    assert hand.stats()["frame_errors"] == {"range": 2} and hand.stats()["cycles"] == 0
    clock.t = 1.0
    finger(hand, 0, edge)
    assert hand.stats()["cycles"] == 1 and hand.stats()["duplicates"] == 0
    assert len(frames(spare)) == 4  # one cycle: 4 torque frames
    finger(hand, 2, q)
    clock.t += PERIOD
    finger(hand, 2, q)  # a new batch before the last completed: dropped, counted once
    assert hand.stats()["duplicates"] == 1 and hand.stats()["cycles"] == 2
    clock.t += PERIOD
    for f in (0, 1, 3):
        finger(hand, f, q)
    assert hand.stats()["cycles"] == 3 and hand.stats()["duplicates"] == 1


def test_temperature_at_the_limit_is_allowed_above_it_trips(bench):
    hand, spare, clock = bench
    hand._handle(Temperature(3, (70, 70, 70, 70)))
    assert hand.state().fault is None
    hand._handle(Temperature(3, (70, 71, 70, 70)))
    assert hand.state().fault == "finger 3 joint temperature 71 C"


def test_a_hand_with_another_device_id_hears_its_own_frames_only():
    channel = f"allegro-id-{uuid.uuid4().hex}"
    host, spare = (can.Bus(interface="virtual", channel=channel) for _ in range(2))
    try:
        hand = AllegroHand(host, device_id=2, config=AllegroConfig(lower=LOWER, upper=UPPER))
        spare.send(encode(Status(0), 0))  # another hand on the bus
        spare.send(encode(Status(0), 2))
        assert hand._recv(1.0) is None and hand._recv(1.0) == Status(0)
        assert hand.stats()["frame_errors"] == {"device": 1}
        hand.command_positions(UPPER)
        hand._send_zero_torque()
        assert all(spare.recv(1.0).arbitration_id & 0x3 == 2 for _ in range(4))
    finally:
        host.shutdown()
        spare.shutdown()


def test_waiting_for_a_reply_still_checks_faults_and_ranges():
    """During the start sequence's waits, a status fault latches and an implausible
    position is counted; the awaited reply is returned."""
    channel = f"allegro-await-{uuid.uuid4().hex}"
    host, spare = (can.Bus(interface="virtual", channel=channel) for _ in range(2))
    try:
        hand = AllegroHand(host, config=AllegroConfig(lower=LOWER, upper=UPPER))
        info = Info(0x0402, 0x0406, False, 40, 0)
        for frame in (Status(0x08), Position(0, (32767, 0, 0, 0)), Position(1, (0, 0, 0, 0)), info):
            spare.send(encode(frame))
        assert hand._await(Info, 1.0) == info
        assert hand.state().fault == "hand status 0x08 reports a fault"
        assert hand.stats()["frame_errors"] == {"range": 1} and hand.stats()["cycles"] == 0
    finally:
        host.shutdown()
        spare.shutdown()


def alive(hand: AllegroHand) -> None:
    """Every finger's temperatures and a status reply reaching the driver now."""
    for f in range(4):
        hand._handle(Temperature(f, (30, 30, 30, 30)))
    hand._handle(Status(0))


@pytest.mark.parametrize("how", ["missing", "out of range"])
def test_a_finger_without_valid_positions_trips_on_its_own(bench, how):
    """Each finger's position stream has its own watchdog: three fingers streaming do not
    cover a fourth whose frames stopped coming or are refused; the stop is sent."""
    hand, spare, clock = bench
    q = on_counts(LOWER + 0.5 * (UPPER - LOWER))
    bad = q.copy()
    bad[9] = UPPER[9] + 0.5  # finger 2, beyond limit + margin
    for k in range(81):  # 240 ms of batches; finger 2 valid only in the first
        clock.t = 1.0 + k * PERIOD
        alive(hand)
        for f in range(4):
            if f != 2 or k == 0:
                finger(hand, f, q)
            elif how == "out of range":
                finger(hand, f, bad)
    assert hand.stats()["cycles"] > 40 and hand.state().fault is None  # the others kept cycling
    frames(spare)
    hand._iterate(clock.t)
    assert hand.state().fault == "finger 2 position stream silent for 240 ms"
    assert frames(spare) == [Torque(f, (0, 0, 0, 0)) for f in range(4)] + [ServoOff()]


def test_every_finger_silent_is_the_stream_silent(bench):
    hand, spare, clock = bench
    clock.t = 1.0
    alive(hand)
    positions(hand, on_counts(LOWER + 0.5 * (UPPER - LOWER)))
    clock.t = 1.25
    hand._iterate(clock.t)
    assert hand.state().fault == "position stream silent for 250 ms"


@pytest.mark.parametrize("celsius, fault", [
    (127, "finger 1 joint temperature 127 C"),
    (-128, "finger 1 joint temperature -128 C: a broken sensor"),
])
def test_an_extreme_temperature_reading_trips_at_once(bench, celsius, fault):
    """127 C (the int8's top) is an over-temperature, not a frame to drop; -128 C a broken
    sensor: both stop the hand on the frame that carries them."""
    hand, spare, clock = bench
    spare.send(encode(Temperature(1, (20, celsius, 20, 20))))
    hand._handle(hand._recv(1.0))
    assert hand.state().fault == fault
    assert frames(spare) == [Torque(f, (0, 0, 0, 0)) for f in range(4)] + [ServoOff()]


def test_status_replies_not_heard_trip(bench):
    hand, spare, clock = bench
    q = on_counts(LOWER + 0.5 * (UPPER - LOWER))
    clock.t = 1.0
    alive(hand)
    for k in range(1, 201):  # positions and temperatures keep coming, the status does not
        clock.t = 1.0 + k * PERIOD
        positions(hand, q)
        for f in range(4):
            hand._handle(Temperature(f, (30, 30, 30, 30)))
    hand._iterate(clock.t)
    assert hand.state().fault == "status not heard for 600 ms"


def test_a_joint_measured_beyond_its_velocity_limit_trips(bench):
    """The mean speed over >= 100 ms against 7 rad/s + 50 %: 10 rad/s passes, also through
    frames read late (a burst at one host time, then on time again); 11 rad/s on one joint
    trips with its name."""
    hand, spare, clock = bench
    q0 = on_counts(LOWER + 0.02 * (UPPER - LOWER))
    alive(hand)
    t_host = 1.0
    for k in range(50):  # the device's sample k at 10 rad/s on joint 5
        if not 20 <= k < 40:  # samples 20..39 are read together, with sample 40
            t_host = 1.0 + k * PERIOD
        clock.t = t_host
        positions(hand, on_counts(q0 + np.r_[np.zeros(5), 10.0 * k * PERIOD, np.zeros(10)]))
    assert hand.state().fault is None and hand.stats()["cycles"] == 50
    q1 = on_counts(q0 + np.r_[np.zeros(5), 10.0 * 49 * PERIOD, np.zeros(10)])
    for k in range(1, 45):
        clock.t += PERIOD
        positions(hand, on_counts(q1 - np.r_[np.zeros(5), 11.0 * k * PERIOD, np.zeros(10)]))
    assert hand.state().fault is not None
    assert hand.state().fault.startswith("joint 5 measured at 11.0 rad/s (limit 7 rad/s)")


@pytest.mark.parametrize("stamped", [True, False])
def test_a_late_read_frame_is_timed_by_its_receive_timestamp(stamped):
    """Joint 5 at 10 rad/s, the window's first frame read 30 ms late (the frames after it in
    a burst), then every other frame lost on the bus. Timed by the frames' receive
    timestamps that is 10 rad/s and no fault; a frame without one falls back to the host's
    time, by which the window is 30 ms short: 12.9 rad/s, beyond 7 rad/s + 50 %."""
    channel = f"allegro-stamps-{uuid.uuid4().hex}"
    host = can.Bus(interface="virtual", channel=channel)
    device = can.Bus(interface="virtual", channel=channel, preserve_timestamps=True)
    clock = FakeClock()
    hand = AllegroHand(host, config=AllegroConfig(lower=LOWER, upper=UPPER), clock=clock)
    q0 = on_counts(LOWER + 0.02 * (UPPER - LOWER))
    try:
        for k in range(0, 60, 2):  # the odd samples are lost
            q = on_counts(q0 + np.r_[np.zeros(5), 10.0 * k * PERIOD, np.zeros(10)])
            msg = encode(Position(1, tuple(int(c) for c in units.rad_to_counts(q[4:8]))))
            msg.timestamp = 5000.0 + k * PERIOD if stamped else 0.0  # the interface's clock
            device.send(msg)
            clock.t = max(1.0 + k * PERIOD, 1.03)  # samples 0..10 read together at 1.03 s
            hand._handle(*hand._receive(1.0))
        fault = hand.state().fault
        if stamped:
            assert fault is None
        else:
            assert fault is not None and fault.startswith("joint 5 measured at 12.9 rad/s")
    finally:
        host.shutdown()
        device.shutdown()
