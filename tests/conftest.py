"""Fixtures shared by the test modules."""

import importlib.util
import os
import signal
import sys
import threading
import time
from pathlib import Path

import pytest
import torch

SCRIPTS = Path(__file__).resolve().parents[1] / "scripts"


@pytest.fixture
def one_torch_thread():
    """Tiny networks run fastest on one thread, and CI shares 2 cores; restores the setting."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


@pytest.fixture
def load_script(monkeypatch):
    """Imports scripts/NAME.py as module NAME, registered in sys.modules for the test (dataclasses
    look their module up there)."""

    def load(name: str):
        spec = importlib.util.spec_from_file_location(name, SCRIPTS / f"{name}.py")
        module = importlib.util.module_from_spec(spec)
        monkeypatch.setitem(sys.modules, name, module)
        spec.loader.exec_module(module)
        return module

    return load


@pytest.fixture
def sigint_storm():
    """A thread (not started) that sends this process SIGINT 200 times ~1 ms apart, as a
    held Ctrl-C; the test's SIGINT handler meanwhile only counts them, and is restored after."""
    counted = []
    previous = signal.signal(signal.SIGINT, lambda signum, frame: counted.append(signum))

    def storm():
        for _ in range(200):
            os.kill(os.getpid(), signal.SIGINT)
            time.sleep(0.001)

    yield threading.Thread(target=storm)
    signal.signal(signal.SIGINT, previous)
