"""Test helper shared by the device tests: poll a condition with a wall-clock timeout."""

import time


def wait_for(pred, timeout: float) -> bool:
    """True as soon as `pred()` holds, polling every 5 ms; its last value after `timeout` s."""
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        if pred():
            return True
        time.sleep(0.005)
    return pred()
