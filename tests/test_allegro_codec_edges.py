"""The Allegro CAN codec at its edges: default device, the last valid and first invalid device,
finger and int16 values, standard ids, empty RTR data, and errors that name the bad field
(mutation testing found these unchecked; see scripts/mutation.py)."""

import pytest

from dexdrake.hardware.allegro_can import (
    Imu,
    Msg,
    Position,
    Request,
    ServoOn,
    SetPosition,
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
