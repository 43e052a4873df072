"""Fuzz the hardware drivers at volume: random and mutated CAN frames into a live Allegro
driver, random and mutated UDP datagrams into a live Z1 client and into the Z1 emulator.

Two placements. By default (`processes`) the setup of `dexdrake real` against emulators:
each driver in its own process (hardware/driver_process.py), each emulator in its own
(hardware/emulator_process.py), on real transports and the wall clock: CAN on python-can's
udp_multicast (the fuzzer is one more node on the group: every frame reaches the driver and
the emulator, as on a bus; some are raw datagrams the transport cannot unpack), the Z1 over
UDP on loopback. The driver's counters come through its process's stats; each frame or
datagram that must latch a fault is timed from its send until the parent sees the fault
(the driver has then sent its safe stop: it trips before it reports). Crashes: a driver or
emulator process that died or exited with a non-zero code. With `--in-process` the drivers
and emulators share this process (a python-can `virtual` bus, loopback UDP), as follows.

CAN: the driver runs its PD loop against the firmware emulator on a python-can `virtual`
bus; a third node sends frames in batches. Each frame is classified by what the driver
must do with it: reject and count it (undecodable, another device, a position beyond the
limits), latch a fault (a status fault bit, a joint hotter than the limit), or accept it.
After each batch the driver must have counted exactly the bad frames and latched a fault
when one was due; a latched fault (also from the emulator obeying fuzzed servo-off or
period frames) is reset, which re-runs the start sequence.
UDP: the client runs against the controller emulator on loopback; datagrams go to the
client's port (mutated RecvState / random bytes: every bad one counted, a motor error or
lost link in a valid one latches a fault) and to the emulator's port (mutated SendCmd /
random bytes: every one it must drop counted, wrong heads included).
Nothing may crash: both drivers' and both emulators' threads must be alive at the end.

    .venv/bin/python scripts/fuzz_hardware.py --frames 100000 --seed 0  # 100k frames + 100k datagrams
"""

from __future__ import annotations

import argparse
import collections
import functools
import re
import signal
import socket
import struct
import sys
import time
import uuid

import can
import numpy as np
from can.interfaces.udp_multicast import UdpMulticastBus
from can.interfaces.udp_multicast.utils import pack_message, unpack_message

from dexdrake.hands import allegro_units as units
from dexdrake.hardware.allegro_can import (
    STATUS_FAULT_BITS,
    AllegroConfig,
    AllegroHand,
    FrameError,
    Imu,
    Info,
    Position,
    Serial,
    ServoOff,
    ServoOn,
    SetPeriod,
    Status,
    Temperature,
    Torque,
    decode,
    default_joint_limits,
    encode,
)
from dexdrake.hardware.allegro_emulator import AllegroEmulator, EmulatorConfig
from dexdrake.hardware.can_bus import open_can_bus, send_on_loopback
from dexdrake.hardware.driver_process import DriverProcess, ProcessConfig, allegro_on_bus, z1_client
from dexdrake.hardware.emulator_process import EmulatorProcess, allegro_emulator, z1_emulator
from dexdrake.hardware.z1_emulator import Z1Emulator, Z1EmulatorConfig
from dexdrake.hardware.z1_udp import (
    ArmFSMState,
    JointCmd,
    JointState,
    MotorState,
    PacketError,
    RecvState,
    SendCmd,
    Z1Arm,
    Z1Config,
    free_udp_port,
)
from dexdrake.hardware.safety import MIN_PLAUSIBLE_TEMPERATURE_C, OVERSPEED_TOLERANCE, HardwareError


def _wait(cond, timeout: float) -> bool:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if cond():
            return True
        time.sleep(0.001)
    return cond()


def _kind(reason: str) -> str:
    """A fault reason without its numbers (for counting faults by kind)."""
    return re.sub(r"0x[0-9a-f]+|-?\d+(\.\d+)?", "#", reason)


def _mutate(data: bytes, rng: np.random.Generator) -> bytes:
    """Flip bits, truncate, extend or overwrite bytes of `data` (1 to 3 mutations)."""
    buf = bytearray(data)
    for _ in range(int(rng.integers(1, 4))):
        kind = int(rng.integers(4))
        if kind == 0 and buf:
            buf[int(rng.integers(len(buf)))] ^= 1 << int(rng.integers(8))
        elif kind == 1 and buf:
            del buf[int(rng.integers(len(buf))):]
        elif kind == 2:
            buf += bytes(rng.integers(0, 256, int(rng.integers(1, 4)), dtype=np.uint8))
        elif buf:
            i = int(rng.integers(len(buf)))
            buf[i] = int(rng.integers(256))
    return bytes(buf)


# ----------------------------------------------------------------------------- CAN
def _valid_can_frame(rng: np.random.Generator, lower: np.ndarray, upper: np.ndarray):
    kind = int(rng.integers(10))
    finger = int(rng.integers(4))
    if kind == 0:
        q = rng.uniform(lower[4 * finger: 4 * finger + 4], upper[4 * finger: 4 * finger + 4])
        return Position(finger, tuple(int(c) for c in units.rad_to_counts(q)))
    if kind == 1:
        return Status(int(rng.integers(0, 0x20)))
    if kind == 2:
        return Temperature(finger, tuple(int(t) for t in rng.integers(-40, 126, 4)))
    if kind == 3:
        return Info(int(rng.integers(0x10000)), int(rng.integers(0x10000)), bool(rng.integers(2)),
                    int(rng.integers(256)), int(rng.integers(0x20)))
    if kind == 4:
        return Serial("".join(chr(int(c)) for c in rng.integers(32, 127, 8)))
    if kind == 5:
        return Imu(tuple(int(v) for v in rng.integers(-32768, 32768, 4)))
    if kind == 6:  # host -> hand frames: the emulator obeys them, the driver ignores them
        return Torque(finger, tuple(int(v) for v in rng.integers(-300, 301, 4)))
    if kind == 7:
        return SetPeriod(int(rng.integers(0, 5)), 0, int(rng.integers(0, 200)))
    return ServoOn() if kind == 8 else ServoOff()


def can_frame(rng: np.random.Generator, lower: np.ndarray, upper: np.ndarray) -> can.Message:
    """A random (30 %) or mutated valid (70 %) CAN frame."""
    if rng.random() < 0.3:
        extended = rng.random() < 0.1
        dlc = int(rng.integers(0, 9))
        if rng.random() < 0.01:
            return can.Message(arbitration_id=0, is_error_frame=True, dlc=0)
        return can.Message(arbitration_id=int(rng.integers(0, 1 << (29 if extended else 11))),
                           is_extended_id=extended, is_remote_frame=bool(rng.random() < 0.05),
                           dlc=dlc, data=bytes(rng.integers(0, 256, dlc, dtype=np.uint8)))
    msg = encode(_valid_can_frame(rng, lower, upper))
    if rng.random() < 0.2:
        return msg  # a valid frame, unchanged
    arb, data, rtr, dlc = msg.arbitration_id, bytes(msg.data), msg.is_remote_frame, msg.dlc
    kind = int(rng.integers(4))
    if kind == 0:
        data = _mutate(data, rng)[:8]
        dlc = len(data) if rng.random() < 0.7 else int(rng.integers(0, 9))
    elif kind == 1:
        arb ^= 1 << int(rng.integers(11))
    elif kind == 2:
        arb = (arb & ~0x3) | int(rng.integers(4))  # another device id
    else:
        rtr, data = True, b""
    return can.Message(arbitration_id=arb, is_extended_id=False, is_remote_frame=rtr, dlc=dlc,
                       data=data)


def classify_can(msg: can.Message, lower: np.ndarray, upper: np.ndarray, cfg: AllegroConfig) -> str:
    """What the driver must do with `msg`: 'bad' (count it), 'fault' (latch) or 'ok'."""
    try:
        frame = decode(msg, 0)
    except FrameError:
        return "bad"
    if isinstance(frame, Position):
        q = units.counts_to_rad(frame.counts)
        sl = slice(4 * frame.finger, 4 * frame.finger + 4)
        m = cfg.position_margin_rad
        if np.any(q < lower[sl] - m) or np.any(q > upper[sl] + m):
            return "bad"
    if isinstance(frame, Status) and frame.bits & STATUS_FAULT_BITS:
        return "fault"
    if isinstance(frame, Temperature) and (max(frame.celsius) > cfg.max_temperature_c
                                           or min(frame.celsius) < MIN_PLAUSIBLE_TEMPERATURE_C):
        return "fault"
    return "ok"


def fuzz_can(frames: int, seed: int, batch: int = 200) -> dict:
    """Push `frames` frames through a live AllegroHand; counters of what happened."""
    rng = np.random.default_rng(seed)
    lower, upper = default_joint_limits()
    channel = f"fuzz-{uuid.uuid4().hex}"
    host, dev, fuzz = (can.Bus(interface="virtual", channel=channel) for _ in range(3))
    cfg = AllegroConfig(watchdog_timeout_s=0.5, temperature_timeout_s=2.0)  # a loaded host
    emu = AllegroEmulator(dev)
    hand = AllegroHand(host, config=cfg)
    out: collections.Counter = collections.Counter()
    faults: collections.Counter = collections.Counter()

    def errors() -> int:
        return sum(hand.stats()["frame_errors"].values())

    t0, cpu0 = time.perf_counter(), time.process_time()
    try:
        with emu, hand:
            _wait(lambda: hand.stats()["cycles"] > 3, 2.0)
            sent = 0
            while sent < frames:
                msgs = [can_frame(rng, lower, upper) for _ in range(min(batch, frames - sent))]
                kinds = [classify_can(m, lower, upper, cfg) for m in msgs]
                expected_bad = kinds.count("bad")
                before = errors()
                for m in msgs:
                    fuzz.send(m)
                sent += len(msgs)
                out.update(kinds)
                if not _wait(lambda: errors() - before >= expected_bad and host.queue.empty(), 5.0):
                    out["uncounted"] += expected_bad - (errors() - before)
                time.sleep(0.002)  # the frame in hand
                out["overcounted"] += max(0, errors() - before - expected_bad)
                if "fault" in kinds and hand.fault.reason is None:
                    out["missed_faults"] += 1
                if hand.fault.reason is not None:
                    faults[_kind(hand.fault.reason)] += 1
                    hand.reset_fault()  # re-runs the start sequence, which ends with servo on
                    if not _wait(lambda: hand.fault.reason is None and emu.servo_on, 2.0):
                        emu.periods = SetPeriod(3, 0, 100)  # fuzz left the emulator mute: recover
                        hand.reset_fault()
                        _wait(lambda: hand.fault.reason is None, 2.0)
            alive = hand.running and emu._thread is not None and emu._thread.is_alive()
            stats = hand.stats()
    finally:
        for b in (host, dev, fuzz):
            b.shutdown()
    return {"frames": sent, "bad": out["bad"], "must_fault": out["fault"], "ok": out["ok"],
            "counted_bad": sum(stats["frame_errors"].values()), "uncounted": out["uncounted"],
            "overcounted": out["overcounted"], "missed_faults": out["missed_faults"],
            "faults_latched": dict(faults), "frame_errors": stats["frame_errors"],
            "emulator_frame_errors": dict(emu.frame_errors), "alive": alive,
            "wall_s": time.perf_counter() - t0, "cpu_s": time.process_time() - cpu0}


# ----------------------------------------------------------------------------- UDP
def _recv_state(rng: np.random.Generator) -> RecvState:
    joints = []
    for _ in range(7):
        motors = tuple(MotorState(int(rng.integers(20, 60)) if rng.random() < 0.99 else int(rng.integers(-128, 128)),
                                  0 if rng.random() < 0.99 else int(rng.integers(256)),
                                  0 if rng.random() < 0.99 else int(rng.integers(256)))
                       for _ in range(2))
        joints.append(JointState(*rng.normal(0, 1, 4), motors))
    return RecvState(ArmFSMState(int(rng.integers(17))), tuple(joints), tuple(rng.normal(0, 1, 6)))


def _send_cmd(rng: np.random.Generator) -> SendCmd:
    joints = tuple(JointCmd(*rng.normal(0, 5, 5)) for _ in range(7))
    head = (0xFE, 0xFF) if rng.random() < 0.8 else tuple(int(b) for b in rng.integers(256, size=2))
    return SendCmd(ArmFSMState(int(rng.integers(17))), joints, bool(rng.integers(2)), head)


def datagram(rng: np.random.Generator, valid: bytes) -> bytes:
    """Random bytes (30 %, any length), `valid` unchanged (20 %) or mutated."""
    r = rng.random()
    if r < 0.3:
        return bytes(rng.integers(0, 256, int(rng.integers(0, 300)), dtype=np.uint8))
    if r < 0.5:
        return valid
    data = _mutate(valid, rng)
    if rng.random() < 0.3:  # non-finite floats where the parser must catch them
        off = int(rng.integers(0, max(1, len(data) - 4)))
        data = data[:off] + struct.pack("<f", [np.nan, np.inf, -np.inf][int(rng.integers(3))]) + data[off + 4:]
    return data


def classify_state(data: bytes, cfg: Z1Config) -> str:
    """'bad', 'fault' (what every state is checked for on arrival) or 'ok' (a state not in
    the client's mode may or may not trip: that check runs on the newest state at a tick)."""
    try:
        st = RecvState.unpack(data)
    except PacketError:
        return "bad"
    joints = st.joints[:6]
    if any(m.error or m.link or not MIN_PLAUSIBLE_TEMPERATURE_C <= m.temperature <= cfg.max_motor_temperature_c
           for j in joints for m in j.motors):
        return "fault"
    if any(abs(j.W) > np.pi * (1 + OVERSPEED_TOLERANCE) for j in joints):
        return "fault"
    return "ok"


def classify_command(data: bytes) -> str:
    try:
        cmd = SendCmd.unpack(data)
    except PacketError:
        return "bad"
    return "ok" if cmd.head == (0xFE, 0xFF) else "bad"


def _udp_batch(rng: np.random.Generator, to_client: bool, n: int, client_config) -> tuple[list[bytes], list[str]]:
    """`n` mutated datagrams and their expected kinds: controller states for the client (judged
    against `client_config`), else client commands for the controller."""
    if to_client:
        data = [datagram(rng, _recv_state(rng).pack()) for _ in range(n)]
        return data, [classify_state(d, client_config) for d in data]
    data = [datagram(rng, _send_cmd(rng).pack()) for _ in range(n)]
    return data, [classify_command(d) for d in data]


def _drain(sock: socket.socket) -> None:
    """Discard whatever was sent back to the fuzzer's socket."""
    while True:
        try:
            sock.recv(4096)
        except BlockingIOError:
            return


def fuzz_udp(datagrams: int, seed: int, batch: int = 50) -> dict:
    """Half the datagrams to a live Z1Arm's port, half to the emulator's; counters."""
    rng = np.random.default_rng(seed)
    emu = Z1Emulator(Z1EmulatorConfig(port=0, client_port=free_udp_port()))
    fuzz = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    fuzz.bind(("127.0.0.1", 0))
    fuzz.setblocking(False)
    out: collections.Counter = collections.Counter()
    faults: collections.Counter = collections.Counter()
    t0, cpu0 = time.perf_counter(), time.process_time()
    emu.start()
    arm = Z1Arm(Z1Config(local_port=emu.config.client_port, controller_port=emu.port, watchdog_timeout_s=0.5))
    try:
        with arm:
            sent = 0
            while sent < datagrams:
                to_client = (sent // batch) % 2 == 0
                n = min(batch, datagrams - sent)
                data, kinds = _udp_batch(rng, to_client, n, arm.config)
                if to_client:
                    counter = lambda: sum(arm.packet_errors.values())  # noqa: E731
                    dest = ("127.0.0.1", arm.local_port)
                else:
                    counter = lambda: sum(emu.packet_errors.values())  # noqa: E731
                    dest = ("127.0.0.1", emu.port)
                expected_bad = kinds.count("bad")
                before = counter()
                for d in data:
                    fuzz.sendto(d, dest)
                sent += n
                out.update(f"{'client' if to_client else 'emulator'}_{k}" for k in kinds)
                if not _wait(lambda: counter() - before >= expected_bad, 5.0):
                    out["uncounted"] += expected_bad - (counter() - before)
                time.sleep(0.003)
                out["overcounted"] += max(0, counter() - before - expected_bad)
                if to_client and "fault" in kinds and arm.fault.reason is None:
                    out["missed_faults"] += 1
                _drain(fuzz)  # the emulator's replies to the fuzzer
                if arm.fault.reason is not None:
                    faults[_kind(arm.fault.reason)] += 1
                    arm.reset_fault()
                    _wait(lambda: arm.fault.reason is None, 2.0)
            alive = arm.running and emu._thread is not None and emu._thread.is_alive()
            client_errors, emu_errors = dict(arm.packet_errors), dict(emu.packet_errors)
    finally:
        emu.stop()
        fuzz.close()
    return {"datagrams": sent,
            **{k: out[k] for k in ("client_bad", "client_fault", "client_ok", "emulator_bad", "emulator_ok")},
            "uncounted": out["uncounted"], "overcounted": out["overcounted"],
            "missed_faults": out["missed_faults"], "faults_latched": dict(faults),
            "client_packet_errors": client_errors, "emulator_packet_errors": emu_errors,
            "alive": alive, "wall_s": time.perf_counter() - t0, "cpu_s": time.process_time() - cpu0}


# ----------------------------------------------------------------------------- processes
START_TIMEOUT_S = 120.0  # a process's spawn and imports, on a loaded host
PROCESS = ProcessConfig(heartbeat_timeout_s=2.0, start_timeout_s=START_TIMEOUT_S)  # the parent fuzzes, its beat may lag


def _free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("", 0))
        return s.getsockname()[1]


def transport_frame(msg: can.Message) -> can.Message | None:
    """`msg` as a udp_multicast receiver gets it, or None when the receiver cannot unpack it
    (python-can checks every message it receives: a DLC that does not match the data, a
    remote error frame)."""
    try:
        return unpack_message(pack_message(msg), check=True)
    except (ValueError, TypeError):
        return None


class SafeStops:
    """Times (s) from the send of a frame or datagram that must latch a fault until the
    parent of the driver's process sees that fault; faults that did not come."""

    def __init__(self) -> None:
        self.times: list[float] = []
        self.missed = 0

    def wait(self, driver: DriverProcess, sent_at: float, timeout: float = 2.0) -> None:
        while driver.state().fault is None:
            if time.perf_counter() - sent_at > timeout:
                self.missed += 1
                return
            time.sleep(0.0002)
        self.times.append(time.perf_counter() - sent_at)

    def report(self) -> dict:
        ms = np.asarray(self.times) * 1e3
        stats = {} if not len(ms) else {"p50_ms": float(np.percentile(ms, 50)),
                                        "p99_ms": float(np.percentile(ms, 99)), "max_ms": float(ms.max())}
        return {"timed": len(ms), **{k: round(v, 1) for k, v in stats.items()}}


def _recover(driver: DriverProcess, nudge=None, attempts: int = 5, timeout: float = 3.0) -> bool:
    """Reset the driver's latched fault until a fault-free state newer than the reset comes
    (fuzzed frames still queued for a loaded driver can fail a reset: its start sequence
    believes them); `nudge()` between attempts. False after `attempts`."""
    for _ in range(attempts):
        t0 = driver.state().t
        driver.reset_fault()
        if _wait(lambda: (st := driver.state()).fault is None and st.t > t0, timeout):
            return True
        if nudge is not None:
            nudge()
    return False


def _ends(driver: DriverProcess, emulator: EmulatorProcess, alive: bool) -> dict:
    """How the processes ended: "crashes" (a driver or emulator process that died while
    fuzzed, an emulator whose thread died, a process that exited with an error or a signal
    its stop did not send), each exit code (-15, -9: the stop escalated, a child that did
    not exit in time after its safe stop, e.g. on a loaded host) and whether the emulator's
    final report came."""
    final = emulator.final
    died = final is not None and not final["running"]
    by_stop = (0, None, -signal.SIGTERM, -signal.SIGKILL)
    bad_exit = sum(code not in by_stop for code in (driver.exitcode, emulator.exitcode))
    return {"crashes": int(not alive) + int(died) + bad_exit, "driver_exitcode": driver.exitcode,
            "emulator_exitcode": emulator.exitcode, "emulator_final_report": final is not None}


def fuzz_can_processes(frames: int, seed: int, batch: int = 50) -> dict:
    """Push `frames` frames (5 % raw datagrams) onto the udp_multicast group of an Allegro
    driver process and its firmware emulator process; counters of what happened."""
    rng = np.random.default_rng(seed)
    lower, upper = default_joint_limits()
    bus = dict(interface="udp_multicast", channel=UdpMulticastBus.DEFAULT_GROUP_IPv4, port=_free_port(),
               receive_own_messages=False)
    cfg = AllegroConfig(watchdog_timeout_s=0.5, temperature_timeout_s=2.0, reply_timeout_s=1.0)  # a loaded host
    fuzz = open_can_bus(bus)
    raw = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    raw.setsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_TTL, 1)
    send_on_loopback(raw)
    emulator = EmulatorProcess(functools.partial(allegro_emulator, bus, EmulatorConfig()),
                               start_timeout_s=START_TIMEOUT_S, name="allegro-emulator")
    hand = DriverProcess(functools.partial(allegro_on_bus, bus, 0, cfg), PROCESS, "Allegro hand")
    out: collections.Counter = collections.Counter()
    faults: collections.Counter = collections.Counter()
    stops = SafeStops()

    def errors() -> int:
        return sum(hand.stats()["frame_errors"].values())

    t0 = time.perf_counter()
    try:
        with emulator, hand:
            _wait(lambda: np.isfinite(hand.state().t), 5.0)
            sent = 0
            while sent < frames:
                items, kinds = [], []
                for _ in range(min(batch, frames - sent)):
                    if rng.random() < 0.05:
                        items.append(bytes(rng.integers(0, 256, int(rng.integers(0, 64)), dtype=np.uint8)))
                        kinds.append("bad")
                        continue
                    msg = can_frame(rng, lower, upper)
                    received = transport_frame(msg)
                    items.append(msg)
                    kinds.append("bad" if received is None else classify_can(received, lower, upper, cfg))
                expected_bad = kinds.count("bad")
                before = errors()
                fault_at = None
                for item, kind in zip(items, kinds):
                    if isinstance(item, bytes):
                        raw.sendto(item, (bus["channel"], bus["port"]))
                    else:
                        fuzz.send(item)
                    if kind == "fault" and fault_at is None:
                        fault_at = time.perf_counter()
                sent += len(items)
                out.update(kinds)
                if fault_at is not None:
                    stops.wait(hand, fault_at)
                if not _wait(lambda: errors() - before >= expected_bad, 5.0):
                    out["uncounted"] += expected_bad - (errors() - before)
                time.sleep(0.002)  # frames still on their way
                out["overcounted"] += max(0, errors() - before - expected_bad)
                fault = hand.state().fault
                if fault is not None:
                    faults[_kind(fault)] += 1
                    # fuzz may have left the emulator mute: set its stream between tries, as a host would
                    out["unrecovered"] += not _recover(hand, lambda: fuzz.send(encode(SetPeriod(
                        cfg.position_period_ms, 0, cfg.temperature_period_ms))))
            alive = hand.running and emulator.exitcode is None
            stats = hand.stats()
    finally:
        fuzz.shutdown()
        raw.close()
    final = emulator.final or {}
    return {"frames": sent, "bad": out["bad"], "must_fault": out["fault"], "ok": out["ok"],
            "counted_bad": sum(stats["frame_errors"].values()), "uncounted": out["uncounted"],
            "overcounted": out["overcounted"], "missed_faults": stops.missed, "unrecovered": out["unrecovered"],
            "faults_latched": dict(faults), "time_to_safe_stop": stops.report(),
            "frame_errors": stats["frame_errors"], "emulator_frame_errors": final.get("frame_errors"),
            **_ends(hand, emulator, alive), "wall_s": time.perf_counter() - t0}


def fuzz_udp_processes(datagrams: int, seed: int, batch: int = 50) -> dict:
    """Half the datagrams to a Z1 client process's port, half to the controller emulator
    process's; counters (the emulator's drops are counted once, from its final report)."""
    rng = np.random.default_rng(seed)
    client = free_udp_port()
    emulator = EmulatorProcess(functools.partial(z1_emulator, Z1EmulatorConfig(port=0, client_port=client)),
                               start_timeout_s=START_TIMEOUT_S, name="z1-emulator")
    fuzz = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    fuzz.bind(("127.0.0.1", 0))
    fuzz.setblocking(False)
    out: collections.Counter = collections.Counter()
    faults: collections.Counter = collections.Counter()
    stops = SafeStops()
    t0 = time.perf_counter()
    try:
        with emulator:
            cfg = Z1Config(local_port=client, controller_port=emulator.report, watchdog_timeout_s=0.5,
                           mode_timeout_s=5.0)
            arm = DriverProcess(functools.partial(z1_client, cfg), PROCESS, "Z1 arm")

            def counter() -> int:
                return sum(arm.stats()["packet_errors"].values())

            with arm:
                sent = 0
                while sent < datagrams:
                    to_client = (sent // batch) % 2 == 0
                    n = min(batch, datagrams - sent)
                    data, kinds = _udp_batch(rng, to_client, n, cfg)
                    if to_client:
                        dest, before = ("127.0.0.1", client), counter()
                    else:
                        dest = ("127.0.0.1", emulator.report)
                    fault_at = None
                    for d, kind in zip(data, kinds):
                        fuzz.sendto(d, dest)
                        if kind == "fault" and fault_at is None:
                            fault_at = time.perf_counter()
                    sent += n
                    out.update(f"{'client' if to_client else 'emulator'}_{k}" for k in kinds)
                    if fault_at is not None:
                        stops.wait(arm, fault_at)
                    if to_client:
                        expected_bad = kinds.count("bad")
                        if not _wait(lambda: counter() - before >= expected_bad, 5.0):
                            out["uncounted"] += expected_bad - (counter() - before)
                        time.sleep(0.003)
                        out["overcounted"] += max(0, counter() - before - expected_bad)
                    else:
                        time.sleep(0.003)
                    _drain(fuzz)
                    fault = arm.state().fault
                    if fault is not None:
                        faults[_kind(fault)] += 1
                        out["unrecovered"] += not _recover(arm)
                alive = arm.running and emulator.exitcode is None
                client_errors = arm.stats()["packet_errors"]
    finally:
        fuzz.close()
    emulator_errors = (emulator.final or {}).get("packet_errors", {})
    return {"datagrams": sent,
            **{k: out[k] for k in ("client_bad", "client_fault", "client_ok", "emulator_bad", "emulator_ok")},
            "uncounted": out["uncounted"], "overcounted": out["overcounted"],
            "emulator_uncounted": out["emulator_bad"] - sum(emulator_errors.values()),
            "missed_faults": stops.missed, "unrecovered": out["unrecovered"], "faults_latched": dict(faults),
            "time_to_safe_stop": stops.report(), "client_packet_errors": client_errors,
            "emulator_packet_errors": emulator_errors, **_ends(arm, emulator, alive),
            "wall_s": time.perf_counter() - t0}


def passed(result: dict) -> bool:
    """Nothing crashed, every bad frame or datagram was counted once, every due fault came."""
    crashed = result["crashes"] if "crashes" in result else not result["alive"]
    return (not crashed and result.get("emulator_final_report", True) and result["uncounted"] == 0 and result["overcounted"] == 0
            and result.get("emulator_uncounted", 0) == 0 and result["missed_faults"] == 0
            and result.get("unrecovered", 0) == 0)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=100_000,
                        help="CAN frames and as many UDP datagrams (default 100000)")
    parser.add_argument("--can", type=int, default=None, help="CAN frames instead (0: skip)")
    parser.add_argument("--udp", type=int, default=None, help="UDP datagrams instead (0: skip)")
    parser.add_argument("--in-process", action="store_true",
                        help="drivers and emulators in this process (virtual CAN bus) instead of their own")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    n_can = args.frames if args.can is None else args.can
    n_udp = args.frames if args.udp is None else args.udp
    runs = ((fuzz_can, fuzz_udp) if args.in_process else (fuzz_can_processes, fuzz_udp_processes))
    ok, crashes = True, 0
    for name, n, run in (("CAN", n_can, runs[0]), ("UDP", n_udp, runs[1])):
        if n <= 0:
            continue
        try:
            result = run(n, args.seed)
        except HardwareError as err:  # a driver or emulator that could not start
            print(f"{name}: FAIL: {err}")
            return 1
        ok &= passed(result)
        crashes += result.get("crashes", int(not result.get("alive", True)))
        print(f"{name} ({'in-process' if args.in_process else 'processes'}): {'PASS' if passed(result) else 'FAIL'}")
        for key, value in result.items():
            print(f"  {key}: {round(value, 2) if isinstance(value, float) else value}")
    print(f"crashes: {crashes}")
    print(f"command: .venv/bin/python scripts/fuzz_hardware.py --can {n_can} --udp {n_udp} --seed {args.seed}"
          + (" --in-process" if args.in_process else ""))
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
