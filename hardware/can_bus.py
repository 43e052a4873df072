"""Opening a python-can bus from its keyword arguments (a scenario's hand entry, a bench's).

`udp_multicast` is the bus that the emulators and drivers of one machine share across their
processes, so it is kept on the loopback interface: its sockets send there and join the group
there. Left to the routing table, the group goes out of the default interface, and each frame
then also takes that interface's transmit path; on a virtual machine's NIC, serviced by the
host, senders and receivers stall for milliseconds at a time (5 ms stalls several times a
second on a loaded 2-CPU VM), longer than the hand's 3 ms position period. A bus opened with
`can.Bus` directly still hears and is heard (it joined the group on its own interface, where
its frames loop back), through that slow path; a socket that sends to the group without
joining it is heard only through `send_on_loopback`.
"""

from __future__ import annotations

import socket
import struct
from typing import Any

import can

from dexdrake.hardware.safety import HardwareError

LOOPBACK_IPV4 = "127.0.0.1"


def open_can_bus(args: dict[str, Any]) -> can.BusABC:
    """`can.Bus(**args)`, a `udp_multicast` one (an IPv4 group) kept on the loopback interface
    (module docstring); HardwareError naming the bus when it cannot open."""
    name = f"{args.get('interface')}:{args.get('channel')}"
    try:
        bus = can.Bus(**args)
    except (can.CanError, OSError, ValueError, ImportError) as err:
        raise HardwareError(f"cannot open CAN bus {name}: {err}") from None
    if args.get("interface") == "udp_multicast":
        try:
            _join_on_loopback(bus, name)
        except (OSError, HardwareError) as err:
            bus.shutdown()
            raise HardwareError(f"cannot keep CAN bus {name} on the loopback interface: {err}") from None
    return bus


def send_on_loopback(sock: socket.socket) -> None:
    """Make the IPv4 UDP socket `sock` send its multicast datagrams out of the loopback interface."""
    sock.setsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_IF, socket.inet_aton(LOOPBACK_IPV4))


def _join_on_loopback(bus: can.BusABC, name: str) -> None:
    """Send out of the loopback interface and move the group membership there (python-can
    joins on any interface, which the routing table resolves, and names none in its API: its
    socket is reached through the bus's `_multicast`)."""
    multicast = bus._multicast
    sock, group = multicast._socket, multicast.group
    if sock.family != socket.AF_INET:
        raise HardwareError(f"{group} is not an IPv4 group (Linux's loopback interface carries IPv4 multicast only)")
    send_on_loopback(sock)
    address = socket.inet_aton(group)
    sock.setsockopt(socket.IPPROTO_IP, socket.IP_DROP_MEMBERSHIP, address + struct.pack("@I", socket.INADDR_ANY))
    sock.setsockopt(socket.IPPROTO_IP, socket.IP_ADD_MEMBERSHIP, address + socket.inet_aton(LOOPBACK_IPV4))
