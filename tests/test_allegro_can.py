"""Allegro v4 CAN codec, driver and emulator on python-can's virtual bus."""

import contextlib
import itertools
import os
import signal
import time
import uuid

import can
import numpy as np
import pytest

from dexdrake.hardware.allegro_can import (
    AllegroConfig,
    AllegroHand,
    FrameError,
    Imu,
    Info,
    Msg,
    Position,
    Request,
    Serial,
    ServoOff,
    ServoOn,
    SetPeriod,
    SetPosition,
    Status,
    Temperature,
    Torque,
    check_allegro_config,
    decode,
    encode,
)
from dexdrake.hardware.allegro_emulator import AllegroEmulator, EmulatorConfig
from dexdrake.hardware.safety import HardwareError
from waiting import wait_for

# spec table (allegro_v4.md), bus order: index, middle, ring (same limits), thumb
FINGER_LO, FINGER_HI = [-0.47, -0.196, -0.174, -0.227], [0.47, 1.61, 1.709, 1.618]
LOWER = np.array(FINGER_LO * 3 + [0.263, -0.105, -0.189, -0.162])
UPPER = np.array(FINGER_HI * 3 + [1.396, 1.163, 1.644, 1.719])


def msg(arb: int, data: bytes = b"", rtr: bool = False, dlc: int | None = None) -> can.Message:
    return can.Message(arbitration_id=arb, is_extended_id=False, is_remote_frame=rtr, data=data,
                       dlc=len(data) if dlc is None else dlc)


@pytest.fixture
def channel():
    return f"allegro-{uuid.uuid4().hex}"


@pytest.fixture
def rig(channel):
    """(hand, emulator, spare bus) on one virtual channel; everything shut down afterwards."""
    host = can.Bus(interface="virtual", channel=channel)
    dev = can.Bus(interface="virtual", channel=channel)
    spare = can.Bus(interface="virtual", channel=channel)
    q0 = np.clip(np.zeros(16), LOWER, UPPER)
    emu = AllegroEmulator(dev, config=EmulatorConfig(lower=LOWER, upper=UPPER, q0=q0))
    # a watchdog and reply wait generous enough for a loaded 2-core CI machine (a reset
    # re-runs the start sequence); stalls below are longer
    hand = AllegroHand(host, config=AllegroConfig(lower=LOWER, upper=UPPER, watchdog_timeout_s=0.2,
                                                  reply_timeout_s=1.0))
    emu.start()
    yield hand, emu, spare
    hand.stop()
    emu.stop()
    for b in (host, dev, spare):
        b.shutdown()


# ------------------------------------------------------------------ codec
FRAMES = [
    ServoOn(), ServoOff(), Torque(2, (1, -2, 300, -1200)), SetPosition(1, (5, 6, 7, -8)),
    SetPeriod(3, 0, 100), SetPeriod(3, 10, 100, 50), Info(0x0402, 0x0406, False, 60, 5),
    Serial("SAH040C0"), Position(3, (-566, 0, 32767, -32768)), Imu((16384, 0, -1, 1)),
    Temperature(1, (35, -5, 60, 100)), Status(0x1F),
    Request(Msg.INFO), Request(Msg.SERIAL), Request(Msg.STATUS), Request(Msg.IMU),
    Request(Msg.POSITION, 2), Request(Msg.TEMPERATURE, 3),
]


@pytest.mark.parametrize("frame", FRAMES, ids=lambda f: type(f).__name__)
@pytest.mark.parametrize("device", [0, 3])
def test_codec_round_trip(frame, device):
    m = encode(frame, device)
    assert m.arbitration_id & 0x3 == device and not m.is_extended_id
    assert decode(m, device) == frame


def test_ids_match_spec_table():
    expect = {ServoOn(): 0x100, ServoOff(): 0x104, Torque(0, (0,) * 4): 0x180,
              Torque(3, (0,) * 4): 0x18C, SetPosition(0, (0,) * 4): 0x380, SetPeriod(3): 0x204,
              Request(Msg.INFO): 0x200, Request(Msg.SERIAL): 0x220,
              Position(0, (0,) * 4): 0x080, Position(3, (0,) * 4): 0x08C,
              Request(Msg.IMU): 0x0C0, Temperature(0, (0,) * 4): 0x0E0, Status(0): 0x040}
    for frame, arb in expect.items():
        assert encode(frame).arbitration_id == arb, frame
    assert encode(SetPeriod(3)).dlc == 6 and encode(SetPeriod(3, 0, 0, 0)).dlc == 8
    assert encode(Request(Msg.INFO)).dlc == 7 and encode(Request(Msg.INFO)).is_remote_frame


def test_spec_real_frames():
    info = decode(msg(0x200, bytes.fromhex("02 04 06 04 00 3C 05")))
    assert info == Info(hw_version=0x0402, fw_version=0x0406, left_hand=False,
                        palm_temperature_c=60, status=5)
    pos = decode(msg(0x080, bytes.fromhex("CA FD 00 00 00 00 00 00")))
    assert pos == Position(0, (-566, 0, 0, 0))
    assert decode(msg(0x080, rtr=True, dlc=8)) == Request(Msg.POSITION, 0)
    torque = encode(Torque(3, (600, 0, 0, 0)))
    assert torque.arbitration_id == 0x18C and bytes(torque.data[:2]) == bytes.fromhex("58 02")


@pytest.mark.parametrize("m, kind", [
    (msg(0x080, b"\x00" * 7), "dlc"),
    (msg(0x100, b"\x01"), "dlc"),
    (msg(0x204, b"\x00" * 4), "dlc"),
    (msg(0x1E8, b""), "unknown_id"),
    (msg(0x081, b"\x00" * 8), "device"),
    (msg(0x040, b"\x20"), "range"),
    (msg(0x200, bytes.fromhex("02 04 06 04 02 3C 05")), "range"),
    (msg(0x220, b"AB\x01CDEFG"), "range"),
    (msg(0x100, rtr=True, dlc=0), "rtr"),
    (can.Message(arbitration_id=0x080, is_extended_id=True, data=b"\x00" * 8), "id"),
])
def test_decode_rejects_with_specific_kind(m, kind):
    with pytest.raises(FrameError) as err:
        decode(m)
    assert err.value.kind == kind


@pytest.mark.parametrize("frame", [
    Torque(4, (0,) * 4), Torque(0, (40000, 0, 0, 0)), Torque(0, (1, 2, 3)),
    SetPeriod(70000), Serial("TOO-LONG-SERIAL"), Status(0x40), Request(Msg.SERVO_ON),
    Request(Msg.POSITION),
])
def test_encode_rejects_bad_frames(frame):
    with pytest.raises(HardwareError):
        encode(frame)


def test_decode_fuzz_only_raises_frame_error():
    rng = np.random.default_rng(0)
    decoded = 0
    for _ in range(5000):
        dlc = int(rng.integers(0, 9))
        m = can.Message(arbitration_id=int(rng.integers(0, 0x800)), is_extended_id=bool(rng.random() < 0.05),
                        is_remote_frame=bool(rng.random() < 0.1), dlc=dlc,
                        data=bytes(rng.integers(0, 256, dlc, dtype=np.uint8)))
        try:
            decode(m)
            decoded += 1
        except FrameError:
            pass
    assert 0 < decoded < 5000


# ------------------------------------------------------------------ driver + emulator
def test_start_stop_sequence_order(rig):
    hand, emu, _ = rig
    info = hand.start()
    assert info.hw_version == 0x0402 and info.fw_version == 0x0406 and not info.left_hand
    assert info.serial == "AH4EMU01" and info.palm_temperature_c == 60
    assert wait_for(lambda: hand.stats()["cycles"] > 5, 2.0)
    hand.stop()
    assert wait_for(lambda: not emu.servo_on, 1.0)
    polls = (Msg.STATUS, Msg.TEMPERATURE)  # RTR polls of the loop
    seen = [f for f in emu.log if not isinstance(f, Torque)
            and not (isinstance(f, Request) and f.msg in polls)]
    assert seen == [ServoOff(), Request(Msg.INFO), Request(Msg.SERIAL), SetPeriod(3, 0, 100),
                    ServoOn(), SetPeriod(0, 0, 0), ServoOff()]
    last_torques = [f for f in emu.log if isinstance(f, Torque)][-4:]
    assert sorted(f.finger for f in last_torques) == [0, 1, 2, 3]
    assert all(f.pwm == (0, 0, 0, 0) for f in last_torques)


@contextlib.contextmanager
def station(channel, **emulator):
    """(hand, emulator) on one virtual channel, the emulator running with `emulator`'s settings."""
    host = can.Bus(interface="virtual", channel=channel)
    dev = can.Bus(interface="virtual", channel=channel)
    emu = AllegroEmulator(dev, config=EmulatorConfig(lower=LOWER, upper=UPPER, **emulator))
    hand = AllegroHand(host, config=AllegroConfig(lower=LOWER, upper=UPPER, watchdog_timeout_s=0.2,
                                                  reply_timeout_s=1.0))
    try:
        with emu:
            yield hand, emu
            hand.stop()
    finally:
        host.shutdown()
        dev.shutdown()


def test_start_holds_the_measured_position_and_reports_the_hand(channel):
    """Until commanded, the hand holds where it was found (not zero, not the middle)."""
    q0 = LOWER + 0.2 * (UPPER - LOWER)
    with station(channel, q0=q0, info=Info(0x0403, 0x0407, True, 45, 0x01)) as (hand, emu):
        info = hand.start()
        assert (info.hw_version, info.fw_version, info.left_hand, info.palm_temperature_c, info.status) == \
            (0x0403, 0x0407, True, 45, 0x01)
        assert wait_for(lambda: hand.stats()["cycles"] > 20, 2.0)
        time.sleep(0.2)
        np.testing.assert_allclose(hand.state().q_target, q0, atol=0.005)
        np.testing.assert_allclose(emu.q, q0, atol=0.01)
        assert hand.stats()["duplicates"] == 0


def test_a_hot_palm_at_start_keeps_the_hand_off(channel):
    with station(channel, info=Info(0x0402, 0x0406, False, 80, 0)) as (hand, emu):
        with pytest.raises(HardwareError, match=r"palm at 80 C at start \(limit 70.0 C\)"):
            hand.start()
        assert not emu.servo_on and not hand.running


@pytest.mark.parametrize("bits", [0x02, 0x08, 0x10, 0x1B])
def test_a_fault_in_the_info_reply_keeps_the_hand_off(channel, bits):
    """A hand that already reports a fault is never switched on (not first at the status poll)."""
    with station(channel, info=Info(0x0402, 0x0406, False, 40, bits)) as (hand, emu):
        with pytest.raises(HardwareError, match=f"hand status {bits:#04x} reports a fault at start"):
            hand.start()
        assert not emu.servo_on and not hand.running


def test_temperatures_never_heard_after_start_trip(channel):
    with station(channel) as (hand, emu):
        emu.inject.mute_temperature = True
        hand.start()
        assert wait_for(lambda: hand.state().fault is not None, 2.0)
        assert "temperature not heard" in hand.state().fault
        assert wait_for(lambda: not emu.servo_on, 0.5)


def test_start_fails_cleanly_without_a_hand(channel):
    host = can.Bus(interface="virtual", channel=channel)
    try:
        hand = AllegroHand(host, config=AllegroConfig(lower=LOWER, upper=UPPER, reply_timeout_s=0.05))
        with pytest.raises(HardwareError, match="no Info reply"):
            hand.start()
        assert not hand.running
    finally:
        host.shutdown()


def test_pd_loop_tracks_target(rig):
    hand, emu, _ = rig
    target = LOWER + 0.6 * (UPPER - LOWER)
    with hand:
        assert wait_for(lambda: hand.stats()["cycles"] > 3, 1.0)
        hand.command_positions(target)
        assert wait_for(lambda: np.max(np.abs(emu.q - target)) < 0.02, 4.0), emu.q - target
        st = hand.state()
        np.testing.assert_allclose(st.q, target, atol=0.03)
        assert st.fault is None and np.all(np.abs(st.tau_pwm) <= hand.pwm_limit)
        stats = hand.stats()
        assert stats["cycles"] > 10 and stats["rate_hz"] > 0 and stats["max_ms"] >= stats["p50_ms"] > 0
        times = hand.loop_times()
        assert times.size > 10 and np.all(np.diff(times) > 0)
        np.testing.assert_array_equal(hand.loop_times(times[-3])[:2], times[-2:])  # and those since
    assert wait_for(lambda: not emu.servo_on, 1.0)


def test_rate_limit_on_targets(rig):
    """The target moves toward the command at the configured 3 rad/s: not faster (bounded by
    the elapsed time) and not stuck (at least half that rate)."""
    hand, emu, _ = rig
    with hand:
        assert wait_for(lambda: hand.stats()["cycles"] > 3, 1.0)
        start = hand.state().q_target
        t0 = time.monotonic()
        hand.command_positions(UPPER)
        time.sleep(0.1)
        step = np.max(np.abs(hand.state().q_target - start))
        elapsed = time.monotonic() - t0
        # joint 1 is commanded 1.6 rad away: far more than 0.1 s at 3 rad/s. The upper bound
        # allows 20 ms for `start`, a snapshot up to one (possibly delayed) cycle old
        assert 0.5 * 3.0 * 0.1 <= step <= 3.0 * (elapsed + 0.02), (step, elapsed)


def test_watchdog_on_stalled_stream_then_reset(rig):
    hand, emu, _ = rig
    with hand:
        assert wait_for(lambda: hand.stats()["cycles"] > 3, 1.0)
        hand.command_positions(LOWER + 0.5 * (UPPER - LOWER))
        time.sleep(0.05)
        emu.stall(0.6)
        assert wait_for(lambda: hand.state().fault is not None, 1.0)
        assert "silent" in hand.state().fault
        assert wait_for(lambda: not emu.servo_on, 0.5)
        assert np.all(emu.pwm == 0) and np.all(hand.state().tau_pwm == 0)
        # latched: the stream coming back does not clear it
        time.sleep(0.6)
        assert hand.state().fault is not None and not emu.servo_on
        hand.reset_fault()
        assert wait_for(lambda: hand.state().fault is None and emu.servo_on, 3.0)
        target = LOWER + 0.3 * (UPPER - LOWER)
        hand.command_positions(target)
        assert wait_for(lambda: np.max(np.abs(emu.q - target)) < 0.03, 4.0)
        # and the next fault stops the hand again
        hand.command_positions(UPPER)
        assert wait_for(lambda: np.max(np.abs(emu.pwm)) > 0, 1.0)
        emu.stall(0.6)
        assert wait_for(lambda: hand.state().fault is not None, 1.0)
        assert wait_for(lambda: not emu.servo_on and not np.any(emu.pwm), 0.5), emu.pwm


def test_bus_errors_are_counted_and_the_loop_goes_on(rig):
    """Three status polls the bus refuses (a full transmit queue): each counted once under
    its error's name, no fault, the loop still cycling."""
    hand, _, _ = rig
    send, refused = hand.bus.send, []

    def flaky(msg, timeout=None):
        if msg.is_remote_frame and msg.arbitration_id >> 2 == Msg.STATUS and len(refused) < 3:
            refused.append(msg)
            raise can.CanOperationError("transmit buffer full")
        return send(msg, timeout)

    hand.bus.send = flaky
    with hand:
        assert wait_for(lambda: len(refused) == 3, 2.0)
        n = hand.stats()["cycles"]
        assert wait_for(lambda: hand.stats()["cycles"] > n + 10, 1.0)
        s = hand.stats()
        assert s["frame_errors"] == {"bus:CanOperationError": 3} and s["fault"] is None, s
        assert hand.running


def test_over_temperature_stops_hand(rig):
    hand, emu, _ = rig
    with hand:
        assert wait_for(lambda: hand.stats()["cycles"] > 3, 1.0)
        emu.set_over_temperature()
        assert wait_for(lambda: hand.state().fault is not None, 1.0)
        assert "temperature" in hand.state().fault or "status" in hand.state().fault
        assert wait_for(lambda: not emu.servo_on, 0.5)


def test_nan_and_out_of_range_commands(rig):
    hand, emu, _ = rig
    with hand:
        assert wait_for(lambda: hand.stats()["cycles"] > 3, 1.0)
        good = LOWER + 0.4 * (UPPER - LOWER)
        np.testing.assert_allclose(hand.command_positions(good), good)
        bad = good.copy()
        bad[5] = np.nan
        np.testing.assert_allclose(hand.command_positions(bad), good)
        np.testing.assert_allclose(hand.command_positions(np.full(16, np.inf)), good)
        # clamped the configured margin (0.02 rad by default) inside the joint limits
        np.testing.assert_allclose(hand.command_positions(np.full(16, 10.0)), UPPER - 0.02)
        np.testing.assert_allclose(hand.command_positions(np.full(16, -10.0)), LOWER + 0.02)
        s = hand.stats()
        assert s["rejected_commands"] == 2 and s["clamped_commands"] == 2
        with pytest.raises(HardwareError):
            hand.command_positions(np.zeros(15))
        assert wait_for(lambda: np.max(np.abs(emu.q - LOWER - 0.02)) < 0.03, 4.0)
        assert hand.state().fault is None


def test_fuzzed_bus_never_crashes_driver(rig):
    hand, emu, spare = rig
    rng = np.random.default_rng(1)
    with hand:
        assert wait_for(lambda: hand.stats()["cycles"] > 3, 1.0)
        # position frames, out of order and duplicated, plus garbage of every kind
        for f in itertools.chain([3, 1, 1, 0, 2, 2], range(4)):
            spare.send(encode(Position(f, (0, 0, 0, 0))))
        spare.send(msg(0x081, b"\x00" * 8))  # wrong device
        spare.send(msg(0x080, b"\x00" * 3))  # short
        spare.send(msg(0x1E8, b"\x01"))  # unknown id
        spare.send(msg(0x080, b"\xff\x7f" * 4))  # 2.9 rad: implausible
        for _ in range(400):
            dlc = int(rng.integers(0, 9))
            arb = int(rng.integers(0, 0x800))
            if arb >> 2 == Msg.STATUS:
                continue  # a random but valid status frame may legitimately report a fault
            spare.send(can.Message(arbitration_id=arb, is_extended_id=False, dlc=dlc,
                                   is_remote_frame=bool(rng.random() < 0.1),
                                   data=bytes(rng.integers(0, 256, dlc, dtype=np.uint8))))
        time.sleep(0.2)
        assert hand.running
        s = hand.stats()
        for kind in ("device", "dlc", "unknown_id", "range"):
            assert s["frame_errors"].get(kind, 0) >= 1, s
        assert s["duplicates"] >= 2
        n = s["cycles"]
        assert wait_for(lambda: hand.stats()["cycles"] > n + 20, 1.0)


def test_emulator_drops_and_corruption_are_counted_and_tolerated(channel):
    host = can.Bus(interface="virtual", channel=channel)
    dev = can.Bus(interface="virtual", channel=channel)
    emu = AllegroEmulator(dev, config=EmulatorConfig(lower=LOWER, upper=UPPER, q0=LOWER + 0.1))
    emu.inject.drop_rate, emu.inject.corrupt_rate = 0.05, 0.1
    hand = AllegroHand(host, config=AllegroConfig(lower=LOWER, upper=UPPER, watchdog_timeout_s=0.2))
    try:
        with emu, hand:
            target = LOWER + 0.5 * (UPPER - LOWER)
            hand.command_positions(target)
            assert wait_for(lambda: np.max(np.abs(emu.q - target)) < 0.03, 8.0)  # a loaded host
            s = hand.stats()
            assert hand.state().fault is None
            for kind in ("dlc", "device", "unknown_id", "range"):
                assert s["frame_errors"].get(kind, 0) >= 1, s
            assert emu.inject.counts["dropped"] >= 1
    finally:
        host.shutdown()
        dev.shutdown()


def test_emulator_keeps_the_last_pwm_on_host_silence(rig):
    """specs/allegro_v4.md: nothing says the firmware stops; the default emulator does not."""
    _, emu, spare = rig
    spare.send(encode(ServoOn()))
    spare.send(encode(Torque(0, (100, 100, 100, 100))))
    assert wait_for(lambda: emu.pwm[0] == 100, 0.5)
    time.sleep(0.3)
    assert emu.servo_on and np.all(emu.pwm[:4] == 100)


def test_emulator_torque_timeout_only_as_an_option(channel):
    host = can.Bus(interface="virtual", channel=channel)
    dev = can.Bus(interface="virtual", channel=channel)
    emu = AllegroEmulator(dev, config=EmulatorConfig(lower=LOWER, upper=UPPER, torque_timeout_s=0.05))
    try:
        with emu:
            host.send(encode(ServoOn()))
            host.send(encode(Torque(0, (100, 100, 100, 100))))
            assert wait_for(lambda: emu.pwm[0] == 100, 0.5)
            assert wait_for(lambda: np.all(emu.pwm == 0), 0.5)
    finally:
        host.shutdown()
        dev.shutdown()


def _fail_loop(hand, emu):
    def broken(*frame_and_stamp):
        raise RuntimeError("boom")

    hand._handle = broken


# every way the host learns of trouble; the emulator keeps the last PWM on its own
FAULTS = {
    "stalled position stream": (lambda hand, emu: emu.stall(5.0), "silent"),
    "over-temperature": (lambda hand, emu: emu.set_over_temperature(), "temperature|status"),
    "temperatures not heard": (lambda hand, emu: setattr(emu.inject, "mute_temperature", True),
                               "temperature not heard"),
    "power loss": (lambda hand, emu: emu.power_cycle(), "silent"),
    "one finger's positions missing": (lambda hand, emu: setattr(emu.inject, "mute_fingers", frozenset({1})),
                                       "finger 1 position stream silent"),
    "status not heard": (lambda hand, emu: setattr(emu.inject, "mute_status", True), "status not heard"),
    "driver loop error": (_fail_loop, "driver loop failed"),
}


class _Blocked:
    """Joints held where they are (the fingers closed on an object): the PD pushes hard."""

    def __init__(self, q: np.ndarray):
        self.q = np.asarray(q, float)

    def step(self, pwm: np.ndarray, dt: float) -> tuple[np.ndarray, np.ndarray]:
        return self.q.copy(), np.zeros_like(self.q)


@pytest.mark.parametrize("fault", list(FAULTS))
def test_host_stops_the_hand_on_every_fault_path(rig, fault):
    """With the spec's firmware (the last PWM stays applied), each fault ends with the host
    sending zero torque and servo off, while the hand was pushing hard before it."""
    hand, emu, _ = rig
    emu.dynamics = _Blocked(emu.q)
    inject, reason = FAULTS[fault]
    with hand:
        assert wait_for(lambda: hand.stats()["cycles"] > 3, 1.0)
        hand.command_positions(UPPER)
        assert wait_for(lambda: np.max(np.abs(emu.pwm)) > 100, 1.0)
        inject(hand, emu)
        assert wait_for(lambda: hand.state().fault is not None, 2.0)
        assert wait_for(lambda: not emu.servo_on and not np.any(emu.pwm), 0.5), emu.pwm
        assert hand.state().fault is not None
        import re

        assert re.search(reason, hand.state().fault), hand.state().fault


def test_reset_after_power_loss_reruns_the_start_sequence(rig):
    hand, emu, _ = rig
    with hand:
        assert wait_for(lambda: hand.stats()["cycles"] > 3, 1.0)
        emu.power_cycle()
        assert wait_for(lambda: hand.state().fault is not None, 1.0)
        n_info = sum(f == Request(Msg.INFO) for f in emu.log)
        hand.reset_fault()
        assert wait_for(lambda: hand.state().fault is None and emu.servo_on, 3.0)
        assert sum(f == Request(Msg.INFO) for f in emu.log) == n_info + 1
        assert emu.periods.position_ms == 3
        time.sleep(0.3)  # streaming again: no new trip
        assert hand.state().fault is None
        target = LOWER + 0.3 * (UPPER - LOWER)
        hand.command_positions(target)
        assert wait_for(lambda: np.max(np.abs(emu.q - target)) < 0.03, 4.0)


def test_reset_of_an_unpowered_hand_trips_again(rig):
    hand, emu, _ = rig
    with hand:
        assert wait_for(lambda: hand.stats()["cycles"] > 3, 1.0)
        emu.inject.silent = True
        assert wait_for(lambda: hand.state().fault is not None, 1.0)
        hand.reset_fault()
        assert wait_for(lambda: "reset failed" in (hand.state().fault or ""), 5.0)
        assert not emu.servo_on


def test_non_numeric_command_raises_the_drivers_error(rig):
    hand, _, _ = rig
    with hand:
        with pytest.raises(HardwareError, match="numbers"):
            hand.command_positions(["open"] * 16)


@pytest.mark.parametrize("kw, message", [
    ({"pwm_limit": [1000.0] * 16}, r"pwm_limit\[0\] = 1000 exceeds the vendor PWM limit 375"),
    ({"kp": [500, 800, 900, 500] * 3 + [1000, 700, 600, 601]}, r"kp\[15\] = 601 exceeds the vendor gain 600"),
    ({"kd": [-1.0] * 16}, "kd must be >= 0"),
    ({"max_target_rate": 1e9}, r"max_target_rate 1e\+09 rad/s must be in \(0, 7\]"),
    ({"lower": LOWER - 0.1, "upper": UPPER}, "reach outside the model"),
    ({"status_poll_s": 0.0}, "status_poll_s must be > 0"),
    ({"pwm_limit": ["x"] * 16}, "need 16 numbers"),
    ({"kd": [26.0] * 16}, r"Allegro kd\[0\] = 26 exceeds the vendor gain 25"),
    ({"kp": [1.0] * 15}, r"Allegro kp: need 16 finite values \(bus order\)"),
    ({"lower": LOWER[:15]}, r"Allegro lower: need 16 finite values"),
    ({"upper": np.r_[UPPER[:15], np.nan]}, r"Allegro upper: need 16 finite values"),
    ({"upper": UPPER + 0.1}, "reach outside the model"),
    ({"max_target_rate": 0.0}, r"max_target_rate 0 rad/s must be in \(0, 7\]"),
    ({"watchdog_timeout_s": -1.0}, r"Allegro watchdog_timeout_s must be > 0, got -1.0"),
    ({"temperature_timeout_s": 0.0}, r"Allegro temperature_timeout_s must be > 0, got 0.0"),
    ({"reply_timeout_s": float("inf")}, r"Allegro reply_timeout_s must be > 0, got inf"),
])
def test_config_beyond_the_limits_is_refused(kw, message):
    with pytest.raises(HardwareError, match=message):
        check_allegro_config(AllegroConfig(**kw))


def test_config_within_the_limits_is_taken_as_given():
    """Zero gains, narrower joint limits and target rates from slow up to the joints' own
    velocity limit (7 rad/s) are all allowed, and used as given."""
    kp, kd = np.full(16, 0.5), np.zeros(16)
    settings = check_allegro_config(AllegroConfig(kp=kp, kd=kd, lower=LOWER + 0.1, upper=UPPER - 0.1))
    np.testing.assert_array_equal(settings.kp, kp)
    np.testing.assert_array_equal(settings.kd, kd)
    np.testing.assert_array_equal(settings.lower, LOWER + 0.1)
    np.testing.assert_array_equal(settings.upper, UPPER - 0.1)
    for rate in (0.5, 7.0):
        check_allegro_config(AllegroConfig(max_target_rate=rate))


class RecordingDynamics:
    """A JointDynamics that records what it is stepped with and reports a fixed pose."""

    def __init__(self, q: np.ndarray):
        self.q, self.calls = q, []

    def step(self, pwm, dt):
        self.calls.append((np.array(pwm), dt))
        return self.q.copy(), np.zeros(16)


def test_emulator_dynamics_hook_gets_the_effective_pwm_and_streams_its_state(channel):
    """Driven by `poll` on a fake clock: the hook sees the PWM of the torque frames, zero
    after the torque timeout; position frames carry the hook's q; a position batch is
    pending until all 4 fingers' torque frames answer it."""
    host = can.Bus(interface="virtual", channel=channel)
    dev = can.Bus(interface="virtual", channel=channel)
    now = [0.0]
    q = np.clip(np.linspace(-0.2, 0.9, 16), LOWER, UPPER)
    dynamics = RecordingDynamics(q)
    emu = AllegroEmulator(dev, config=EmulatorConfig(lower=LOWER, upper=UPPER, torque_timeout_s=0.05),
                          clock=lambda: now[0], dynamics=dynamics)  # the optional cut-off
    try:
        for frame in (SetPeriod(3), ServoOn(), Torque(3, (100, -50, 0, 7))):
            host.send(encode(frame))
        emu.poll(0.0, 0.05)
        now[0] = 0.002
        emu.poll(now[0])
        pwm, dt = dynamics.calls[-1]
        assert dt == pytest.approx(0.002)
        np.testing.assert_array_equal(pwm[12:], [100, -50, 0, 7])
        frames = [decode(host.recv(0.5)) for _ in range(4)]
        got = np.concatenate([np.array(f.counts) for f in sorted(frames, key=lambda f: f.finger)])
        np.testing.assert_allclose(got * 333.3 / 65536 * np.pi / 180, q, atol=1e-4)
        assert emu.torque_pending
        for f in range(4):
            host.send(encode(Torque(f, (1, 2, 3, 4))))
        emu.poll(now[0], 0.05)
        assert not emu.torque_pending
        now[0] = 0.2  # no torque frame for longer than the timeout: the hook gets zero PWM
        emu.poll(now[0])
        assert not np.any(dynamics.calls[-1][0])
    finally:
        host.shutdown()
        dev.shutdown()


def test_default_limits_come_from_hand_description_in_bus_order():
    from dexdrake.hardware.allegro_can import default_joint_limits

    lo, hi = default_joint_limits()
    np.testing.assert_allclose(lo, LOWER)
    np.testing.assert_allclose(hi, UPPER)


def test_restart_refused_while_fault_latched(rig):
    hand, emu, _ = rig
    hand.start()
    emu.stall(0.6)
    assert wait_for(lambda: hand.state().fault is not None, 1.0)
    hand.stop()
    with pytest.raises(HardwareError, match="fault latched"):
        hand.start()
    hand.reset_fault()
    time.sleep(0.6)  # the stall is over
    hand.start()
    assert wait_for(lambda: hand.stats()["cycles"] > 3 and emu.servo_on, 3.0)  # generous: a loaded host
    assert hand.state().fault is None


def test_emulator_answers_info_with_the_spec_frame(rig):
    _, _, spare = rig
    spare.send(encode(Request(Msg.INFO)))
    reply = spare.recv(1.0)
    assert reply.arbitration_id == 0x200 and bytes(reply.data) == bytes.fromhex("02 04 06 04 00 3C 05")


def test_ctrl_c_leads_to_safe_stop(rig):
    hand, emu, _ = rig
    with pytest.raises(KeyboardInterrupt):
        with hand:
            assert wait_for(lambda: emu.servo_on, 1.0)
            os.kill(os.getpid(), signal.SIGINT)
            time.sleep(1.0)  # interrupted by the signal
    assert not hand.running
    assert wait_for(lambda: not emu.servo_on and emu.periods.position_ms == 0, 1.0)


def test_a_storm_of_ctrl_c_never_aborts_the_safe_stop(rig, sigint_storm):
    """SIGINT 200 times ~1 ms apart while the hand pushes hard on a busy bus: one KeyboardInterrupt, and
    the stop runs to its end: zero torque first (no other torque after it), then the
    stream off (period 0) and servo off."""
    hand, emu, _ = rig
    emu.dynamics = _Blocked(emu.q)
    send = hand.bus.send

    def slow_send(msg, timeout=None):  # a busy bus: 1 ms a frame, so the stop takes a while
        time.sleep(0.001)
        return send(msg, timeout)

    hand.bus.send = slow_send
    with pytest.raises(KeyboardInterrupt):
        with hand:
            hand.command_positions(UPPER)
            assert wait_for(lambda: np.max(np.abs(emu.pwm)) > 100, 1.0)
            n = len(emu.log)
            sigint_storm.start()
            time.sleep(5.0)
    sigint_storm.join()
    assert not hand.running
    assert wait_for(lambda: not emu.servo_on and emu.periods.position_ms == 0, 1.0)
    assert not np.any(emu.pwm)
    after = list(emu.log)[n:]
    zero = next(i for i, f in enumerate(after) if isinstance(f, Torque) and not any(f.pwm))
    assert all(not any(f.pwm) for f in after[zero:] if isinstance(f, Torque))
    assert after[zero:].index(SetPeriod(0, 0, 0)) < after[zero:].index(ServoOff())


def test_a_message_the_transport_cannot_deliver_is_counted_by_driver_and_emulator():
    """udp_multicast checks every message it receives: a frame whose DLC does not match its
    data (or a datagram that is no message at all) raises in recv. The driver and the emulator count it
    as a bad frame and read on; a valid frame after it still arrives."""
    import socket

    from can.interfaces.udp_multicast import UdpMulticastBus

    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as free:
        free.bind(("", 0))
        port = free.getsockname()[1]
    args = dict(interface="udp_multicast", channel=UdpMulticastBus.DEFAULT_GROUP_IPv4, port=port,
                receive_own_messages=False)
    host, dev, sender = can.Bus(**args), can.Bus(**args), can.Bus(**args)
    try:
        hand, emu = AllegroHand(host), AllegroEmulator(dev)
        sender.send(msg(Msg.STATUS << 2, b"\x01", dlc=8))
        sender.send(encode(Status(0x01)))
        assert hand._recv(2.0) is None and hand._recv(2.0) == Status(0x01)
        assert hand.stats()["frame_errors"] == {"bus:CanOperationError": 1}
        emu.poll(time.monotonic(), 0.5)
        assert wait_for(lambda: (emu.poll(time.monotonic(), 0.05), emu.frame_errors)[1] == {
            "bus:CanOperationError": 1} and Status(0x01) in emu.log, 5.0)
    finally:
        for bus in (host, dev, sender):
            bus.shutdown()


def test_reset_re_arms_at_the_measured_position_and_keeps_a_set_point_sent_after_it(rig):
    """Fingers moved while the hand was off: reset_fault() re-arms holding where they are
    now, not the set-point from before the fault; a set-point sent right after
    reset_fault() is the one followed."""
    hand, emu, _ = rig
    with hand:
        old = LOWER + 0.5 * (UPPER - LOWER)
        hand.command_positions(old)
        assert wait_for(lambda: np.max(np.abs(emu.q - old)) < 0.03, 4.0)
        emu.stall(0.5)
        assert wait_for(lambda: hand.state().fault is not None and not emu.servo_on, 1.0)
        moved = LOWER + 0.2 * (UPPER - LOWER)  # pushed by hand while off
        emu.dynamics.dq, emu.dynamics.q = np.zeros(16), moved.copy()
        assert wait_for(lambda: np.allclose(emu.q, moved, atol=0.01), 1.0)
        time.sleep(0.5)  # the stream is back
        hand.reset_fault()
        assert wait_for(lambda: hand.state().fault is None and emu.servo_on, 3.0)
        time.sleep(0.3)
        np.testing.assert_allclose(hand.state().q_target, moved, atol=0.03)
        np.testing.assert_allclose(emu.q, moved, atol=0.03)
        emu.stall(0.5)
        assert wait_for(lambda: hand.state().fault is not None and not emu.servo_on, 1.0)
        time.sleep(0.5)
        new = LOWER + 0.4 * (UPPER - LOWER)
        hand.reset_fault()
        hand.command_positions(new)
        assert wait_for(lambda: np.max(np.abs(emu.q - new)) < 0.03, 4.0), hand.state()
