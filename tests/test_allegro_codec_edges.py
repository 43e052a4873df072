"""The Allegro CAN codec at its edges: default device, the last valid and first invalid device,
finger and int16 values, standard ids, empty RTR data, and errors that name the bad field
(mutation testing found these unchecked; see scripts/mutation.py)."""

import can
import pytest

from dexdrake.hardware.allegro_can import (
    FrameError,
    Imu,
    Info,
    Msg,
    Position,
    Request,
    Serial,
    ServoOn,
    SetPeriod,
    SetPosition,
    Status,
    Temperature,
    Torque,
    can_id,
    decode,
    encode,
)
from dexdrake.hardware.safety import HardwareError


def test_device_defaults_to_zero_and_stops_at_three():
    assert can_id(Msg.SERVO_ON) == int(Msg.SERVO_ON) << 2
    assert can_id(Msg.SERVO_ON, 3) == (int(Msg.SERVO_ON) << 2) | 3
    assert encode(ServoOn()).arbitration_id == int(Msg.SERVO_ON) << 2
    with pytest.raises(HardwareError, match=r"device_id must be 0\.\.3, got 4"):
        can_id(Msg.SERVO_ON, 4)
    with pytest.raises(HardwareError, match=r"device_id must be 0\.\.3, got -1"):
        encode(ServoOn(), device_id=-1)


def test_finger_errors_name_the_finger():
    with pytest.raises(HardwareError, match=r"finger must be 0\.\.3, got 4"):
        encode(Torque(4, (0, 0, 0, 0)))


@pytest.mark.parametrize("make, name", [(lambda v: Torque(1, v), "torque PWM"),
                                        (lambda v: SetPosition(2, v), "set position"),
                                        (lambda v: Position(0, v), "position"),
                                        (Imu, "IMU")])
def test_int16_payloads_accept_the_full_range_and_nothing_more(make, name):
    for values in [(-32768, 32767, 0, 1), (32767, -32768, -1, 0)]:
        assert decode(encode(make(values))) == make(values)
    for bad in [(-32769, 0, 0, 0), (0, 32768, 0, 0), (0, 0, 0)]:
        with pytest.raises(HardwareError, match=rf"^{name}: need 4 int16 values, got \[.*\]$"):
            encode(make(bad))


def test_frames_use_standard_ids_and_requests_carry_no_data():
    for frame in (ServoOn(), Torque(0, (1, 2, 3, 4)), Request(Msg.POSITION, 2)):
        msg = encode(frame)
        assert msg.is_extended_id is False and msg.arbitration_id <= 0x7FF
    request = encode(Request(Msg.POSITION, 2))
    assert request.is_remote_frame and bytes(request.data) == b"" and request.dlc == 8
    assert encode(Torque(0, (1, 2, 3, 4))).dlc == 8 and encode(ServoOn()).dlc == 0


@pytest.mark.parametrize("good, bad, error", [
    ([SetPeriod(0, 0, 0), SetPeriod(0xFFFF, 1, 2, 0xFFFF)], [SetPeriod(0x10000, 0, 0), SetPeriod(1, 2, 3, -1)],
     "periods must be uint16 ms"),
    ([Info(0, 0, False, 0, 0), Info(0xFFFF, 0xFFFF, True, 255, 0x1F)],
     [Info(-1, 0, False, 0, 0), Info(0x10000, 0, False, 0, 0), Info(0, -1, False, 0, 0),
      Info(0, 0x10000, False, 0, 0), Info(0, 0, False, -1, 0), Info(0, 0, False, 256, 0),
      Info(0, 0, False, 0, -1), Info(0, 0, False, 0, 256)], "info fields out of range"),
    ([Serial(""), Serial("ABCDEFGH")], [Serial("ABCDEFGHI")], "serial is at most 8 ASCII characters"),
    ([Temperature(0, (-40, 125, 0, 1))], [Temperature(0, (-129, 0, 0, 0)), Temperature(0, (0, 128, 0, 0)),
                                          Temperature(0, (1, 2, 3))], "temperatures must be 4 int8"),
    ([Status(0), Status(0x1F)], [Status(0x20), Status(-1)], "status bits must be 0..0x1F"),
    ([Request(Msg.INFO), Request(Msg.TEMPERATURE, 3)], [Request(Msg.TORQUE, 0)], "cannot be requested by RTR"),
    ([], [Request(Msg.POSITION), Request(Msg.STATUS, 1)], "finger must be given exactly for per-finger"),
])
def test_encode_bounds_are_exact_and_errors_name_the_field(good, bad, error):
    for frame in good:
        assert decode(encode(frame)) == frame
    for frame in bad:
        with pytest.raises(HardwareError, match=error):
            encode(frame)


def test_wide_fields_are_unsigned_and_encode_refuses_what_is_not_a_frame():
    # The firmware's extremes: uint16 versions, uint8 temperature and status, int8 temperatures.
    assert bytes(encode(Info(0xFFFF, 0x8000, True, 255, 255)).data) == bytes.fromhex("ffff008001ffff")
    assert bytes(encode(Temperature(1, (-128, 127, 0, -1))).data) == bytes.fromhex("807f00ff")
    assert bytes(encode(Serial("AB")).data) == b"AB\0\0\0\0\0\0"
    with pytest.raises(HardwareError, match="not an Allegro frame: 'x'"):
        encode("x")


def test_frame_errors_say_what_was_wrong():
    bad = can.Message(arbitration_id=can_id(Msg.STATUS), is_extended_id=False, data=b"\x00\x00")
    with pytest.raises(FrameError, match=r"^bad Allegro frame \(dlc\): STATUS with DLC 2") as err:
        decode(bad)
    assert err.value.kind == "dlc"


def _std(arb_id: int, data: bytes = b"", **kw) -> can.Message:
    return can.Message(arbitration_id=arb_id, is_extended_id=False, data=data, **kw)


@pytest.mark.parametrize("msg, kind, text", [
    (_std(0x7FF), "unknown_id", r"id 0x7ff \(message 0x1ff\)"),  # the largest standard id is still an id
    (_std(0x800), "id", "out-of-range id 0x800"),
    (_std(can_id(Msg.POSITION) + (4 << 2), bytes(8)), "unknown_id", "message 0x24"),  # one past finger 3
    (_std(can_id(Msg.TORQUE) + (4 << 2), bytes(8)), "unknown_id", "message 0x64"),
    (_std(can_id(Msg.STATUS), b"\x00", is_error_frame=True), "error_frame", r"\(error_frame\): CAN error frame$"),
    (_std(can_id(Msg.STATUS, 1), b"\x00"), "device", "device 1, expected 0"),
    (_std(can_id(Msg.TORQUE), is_remote_frame=True, dlc=8), "rtr", "TORQUE cannot be requested by RTR"),
    (_std(can_id(Msg.INFO), bytes.fromhex("0100020002001f")), "range", "info hand type 2 / status 0x1f"),
])
def test_decode_refusals_name_kind_and_cause(msg, kind, text):
    with pytest.raises(FrameError, match=text) as err:
        decode(msg)
    assert err.value.kind == kind


def test_decoded_values_keep_their_exact_ranges():
    for text in ("MAX", " A B", "~~~~~~~~"):  # trailing letters survive, space and tilde are printable
        assert decode(encode(Serial(text))) == Serial(text)
    with pytest.raises(FrameError, match="serial is not printable ASCII") as err:
        decode(_std(can_id(Msg.SERIAL), b"AB\x7f\0\0\0\0\0"))
    assert err.value.kind == "range"
    for temps in ((-40, 125, 0, 0), (-128, 127, 0, 0)):  # every int8 is a reading (the driver judges it)
        assert decode(encode(Temperature(2, temps))) == Temperature(2, temps)
    with pytest.raises(FrameError, match="status reserved bits set: 0x20"):
        decode(_std(can_id(Msg.STATUS), b"\x20"))
