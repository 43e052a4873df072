"""Opening CAN buses (hardware/can_bus.py): a udp_multicast group kept on the loopback
interface, where its frames and raw datagrams sent there are heard; a bus that cannot open
is one HardwareError line."""

import socket

import can
import pytest
from can.interfaces.udp_multicast import UdpMulticastBus
from can.interfaces.udp_multicast.utils import pack_message

from dexdrake.hardware.can_bus import open_can_bus, send_on_loopback
from dexdrake.hardware.safety import HardwareError


def _args(group: str = UdpMulticastBus.DEFAULT_GROUP_IPv4) -> dict:
    with socket.socket(socket.AF_INET6 if ":" in group else socket.AF_INET, socket.SOCK_DGRAM) as free:
        free.bind(("", 0))
        port = free.getsockname()[1]
    return dict(interface="udp_multicast", channel=group, port=port, receive_own_messages=False)


def _heard(bus: can.BusABC) -> list[int]:
    ids = []
    while (msg := bus.recv(0.3)) is not None:
        ids.append(msg.arbitration_id)
    return ids


def _message(arbitration_id: int) -> can.Message:
    return can.Message(arbitration_id=arbitration_id, data=b"\x01", is_extended_id=False)


def test_a_udp_multicast_group_is_kept_on_loopback():
    args = _args()
    a, b = open_can_bus(args), open_can_bus(args)
    try:
        sock = a._multicast._socket
        assert sock.getsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_IF, 4) == socket.inet_aton("127.0.0.1")
        a.send(_message(1))
        assert _heard(b) == [1]
        b.send(_message(2))
        assert 2 in _heard(a)  # (after its own frame: udp_multicast loops a sender's frames back to it)
    finally:
        a.shutdown()
        b.shutdown()


def test_a_raw_datagram_sent_on_loopback_is_heard():
    args = _args()
    bus = open_can_bus(args)
    raw = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    try:
        send_on_loopback(raw)
        raw.sendto(pack_message(_message(3)), (args["channel"], args["port"]))
        assert _heard(bus) == [3]
    finally:
        raw.close()
        bus.shutdown()


def test_a_bus_that_cannot_open_is_one_hardware_error():
    with pytest.raises(HardwareError, match="cannot open CAN bus udp_multicast:no.such.group"):
        open_can_bus(dict(interface="udp_multicast", channel="no.such.group", port=1))
    group = UdpMulticastBus.DEFAULT_GROUP_IPv6
    with pytest.raises(HardwareError, match=f"cannot keep CAN bus udp_multicast:{group} on the loopback "
                                            f"interface: {group} is not an IPv4 group"):
        open_can_bus(_args(group))
