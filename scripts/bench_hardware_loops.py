"""Loop rate and jitter of the hardware drivers against their emulators.

Runs the Allegro CAN driver (333 Hz PD loop, python-can virtual bus) and the Z1 UDP client
(500 Hz, loopback) each for a few seconds while they follow a slow sine target, then prints
the achieved rate and the period statistics (mean/p50/p99/max) with ratios against the
named baseline: the nominal period (Allegro: 3 ms position stream; Z1: 2 ms SDK loop).

    .venv/bin/python scripts/bench_hardware_loops.py [--seconds 3]
"""

from __future__ import annotations

import argparse
import time
import uuid

import can
import numpy as np

from dexdrake.hardware.allegro_can import AllegroConfig, AllegroHand, default_joint_limits
from dexdrake.hardware.allegro_emulator import AllegroEmulator, EmulatorConfig
from dexdrake.hardware.z1_emulator import Z1Emulator, Z1EmulatorConfig
from dexdrake.hardware.z1_udp import Z1Arm, Z1Config, free_udp_port


def _follow_sine(command, measure, lower: np.ndarray, upper: np.ndarray, seconds: float) -> float:
    """Command a 0.25 Hz sine inside the limits for `seconds`; RMS tracking error (rad)."""
    mid, amp = (lower + upper) / 2, 0.3 * (upper - lower) / 2
    errors, t0 = [], time.monotonic()
    while (t := time.monotonic() - t0) < seconds:
        target = mid + amp * np.sin(2 * np.pi * 0.25 * t)
        command(target)
        time.sleep(0.01)
        errors.append(measure() - target)
    return float(np.sqrt(np.mean(np.square(errors[len(errors) // 4:]))))


def bench_allegro(seconds: float) -> tuple[dict, float]:
    channel = f"bench-{uuid.uuid4().hex}"
    host = can.Bus(interface="virtual", channel=channel)
    dev = can.Bus(interface="virtual", channel=channel)
    lower, upper = default_joint_limits()
    try:
        with AllegroEmulator(dev, config=EmulatorConfig(lower=lower, upper=upper)) as emu, \
                AllegroHand(host, config=AllegroConfig(lower=lower, upper=upper)) as hand:
            rms = _follow_sine(hand.command_positions, lambda: emu.q, lower, upper, seconds)
            return hand.stats(), rms
    finally:
        host.shutdown()
        dev.shutdown()


def bench_z1(seconds: float) -> tuple[dict, float]:
    from dexdrake.hardware.z1_udp import default_joint_limits as z1_limits

    lower, upper = z1_limits()
    with Z1Emulator(Z1EmulatorConfig(port=0, client_port=free_udp_port(), lower=lower, upper=upper)) as emu, \
            Z1Arm(Z1Config(local_port=emu.config.client_port, controller_port=emu.port, lower=lower,
                           upper=upper)) as arm:
        rms = _follow_sine(arm.command_positions, lambda: emu.q, lower, upper, seconds)
        return arm.stats(), rms


def _report(name: str, stats: dict, rms: float, nominal_ms: float) -> None:
    print(f"\n{name}  (baseline: nominal period {nominal_ms:.3f} ms = {1e3 / nominal_ms:.1f} Hz)")
    print(f"  cycles {stats['cycles']:.0f}, rate {stats['rate_hz']:.1f} Hz "
          f"({stats['rate_hz'] / (1e3 / nominal_ms):.3f} x baseline)")
    for key in ("mean_ms", "p50_ms", "p99_ms", "max_ms"):
        print(f"  period {key[:-3]:>4}: {stats[key]:7.3f} ms  ({stats[key] / nominal_ms:.2f} x baseline)")
    errors = stats["frame_errors"] if "frame_errors" in stats else stats["packet_errors"]
    print(f"  tracking RMS error {rms * 1e3:.2f} mrad; errors {errors}; fault {stats['fault']}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seconds", type=float, default=3.0, help="run time per driver")
    args = parser.parse_args()
    print(f"command: bench_hardware_loops.py --seconds {args.seconds}")
    stats, rms = bench_allegro(args.seconds)
    _report("Allegro v4 CAN PD loop (virtual bus + emulator)", stats, rms, 3.0)
    stats, rms = bench_z1(args.seconds)
    _report("Z1 UDP client loop (loopback + emulator)", stats, rms, 2.0)


if __name__ == "__main__":
    main()
