"""`dexdrake parity`: simulation first, then HIL at the first scale, then the other scales
interleaved episode by episode, the table rewritten after every episode (stand-in episodes:
the command's order and table, not HIL itself)."""

from __future__ import annotations

import hashlib

import numpy as np
import pytest

from dexdrake.cli import main
from dexdrake.errors import DexdrakeError
from dexdrake.paths import models_dir


def test_parity_runs_sim_then_each_scale_and_rewrites_the_table_after_every_episode(tmp_path, monkeypatch, capsys):
    ran, tables = [], []
    out = tmp_path / "parity.md"

    def episode(config, obj, seed, steps, mode, scale, camera):
        if out.is_file():
            tables.append(out.read_text())
        if len(ran) == 6:
            raise DexdrakeError("stopped")
        ran.append((mode, scale, obj, seed))
        return {"object": obj, "seed": seed, "mode": mode, "scale": scale, "success": obj == "can_soda",
                "lift": 0.1 if obj == "can_soda" else 0.0, "fault": "", "wall_s": 1.0, "cpu_s": 1.0,
                "pose_error": [0.002, 0.004] if mode == "sim" else [0.001, 0.003, 0.020]}

    monkeypatch.setattr("dexdrake.systems.parity.run_parity_episode", episode)
    argv = ["parity", "--objects", "can_soda", "sphere_small", "--seeds", "3", "--horizon", "5", "--scales", "1",
            "0.5", "2", "--camera", "sim", "--out", str(out)]
    assert main(argv) == 2  # stopped in the seventh episode
    assert ran == [("sim", 1.0, "can_soda", 3), ("sim", 1.0, "sphere_small", 3), ("hil", 1.0, "can_soda", 3),
                   ("hil", 1.0, "sphere_small", 3), ("hil", 0.5, "can_soda", 3), ("hil", 2.0, "can_soda", 3)]
    assert len(tables) == 6 and tables[0].count("| sim |") == 1 and "| hil |" not in tables[1]
    table = out.read_text()  # the six finished episodes, each HIL row beside simulation on its own episodes
    assert table.startswith("Command: `dexdrake parity --config hil --objects can_soda sphere_small --seeds 3 "
                            "--horizon 5 --scales 1.0 0.5 2.0 --camera sim --out")
    shipped = hashlib.sha256((models_dir() / "weights" / "allegro_z1_dexrep_policy.pt").read_bytes()).hexdigest()
    assert f"Controller: policy `models/weights/allegro_z1_dexrep_policy.pt` (sha256 {shipped[:12]}, DexRep+Vel)." in table
    assert "| sim | - | 2 | 50% | 0.050 | 0 | 3.0 / 4.0 / 4.0 | 50% / 0.050 | can_soda/3 |" in table
    assert "| hil | 1 x | 2 | 50% |" in table
    assert "| hil | 0.5 x | 1 | 100% | 0.100 | 0 | 3.0 / 18.3 / 20.0 | 100% / 0.100 | can_soda/3 |" in table
    assert "stopped" in capsys.readouterr().err


@pytest.mark.parametrize("argv", [["parity", "--scales", "0"], ["parity", "--seeds", "-1"]])
def test_parity_refuses_a_bad_number_before_any_episode(argv, capsys):
    with pytest.raises(SystemExit) as exit_:
        main(argv)
    assert exit_.value.code == 2 and "error: argument --" in capsys.readouterr().err


def test_pose_error_counts_the_steps_the_object_is_on_the_table():
    """The distance between the pose the controller saw and the world's at the sample, while the
    object's centre is above the table top; an object that fell off the table is not counted."""
    from pydrake.math import RigidTransform

    from dexdrake.systems.parity import PoseError

    log, seen = PoseError(), np.array([0.0, 0.0, 0.04, 1.0, 0.0, 0.0, 0.0])
    for z in (0.04, 0.05, -0.3, -0.9):  # the world's object: on the table, lifted, falling past its edge
        log.log_station_step(0.0, None, None, seen, None, RigidTransform([0.0, 0.0, z]))
    assert log.errors == pytest.approx([0.0, 0.01])
