"""The distribution builds, installs as a regular (non-editable) package and finds its data."""

import os
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def installed(tmp_path_factory) -> Path:
    tmp = tmp_path_factory.mktemp("wheel")
    pip = [sys.executable, "-m", "pip", "-q", "--disable-pip-version-check"]
    subprocess.run(pip + ["wheel", "--no-deps", "--no-build-isolation", "-w", str(tmp / "dist"), str(REPO)], check=True)
    (wheel,) = (tmp / "dist").glob("dexdrake-*.whl")
    subprocess.run(pip + ["install", "--no-deps", "--target", str(tmp / "site"), str(wheel)], check=True)
    return tmp / "site"


def _run(site: Path, code: str) -> str:
    env = dict(os.environ, PYTHONPATH=str(site))
    return subprocess.run([sys.executable, "-c", code], env=env, check=True, capture_output=True, text=True,
                          cwd=site).stdout


def test_installed_package_maps_top_level_folders(installed):
    out = _run(installed, "import dexdrake.cli, dexdrake.systems, dexdrake.hardware, dexdrake.models as m; print(m.__file__)")
    assert out.strip().startswith(str(installed))


def test_installed_package_finds_model_files(installed):
    code = (
        "from dexdrake.paths import models_dir\n"
        "from dexdrake.hands.description import hand_names, load_hand\n"
        "names = hand_names()\n"
        "assert {'adroit', 'allegro', 'allegro_z1'} <= set(names), names\n"
        "for n in names: assert load_hand(n).model_path.is_file(), n\n"
        "from dexdrake.objects.library import list_objects\n"
        "objs = list_objects()\n"
        "assert all(o.mesh_path.is_file() for o in objs)\n"
        "print(models_dir(), len(names), len(objs))\n"
    )
    out = _run(installed, code)
    assert out.startswith(str(installed))


def test_no_generic_top_level_names_installed(installed):
    top = {p.name for p in installed.iterdir() if not p.name.endswith(".dist-info")}
    assert top - {"bin"} == {"dexdrake"}, top  # bin/ holds the `dexdrake` console script
    assert (installed / "bin" / "dexdrake").is_file()


def test_installed_package_ships_the_scenarios(installed):
    code = ("from dexdrake.systems.scenario import load_scenario, packaged_scenarios\n"
            "print(packaged_scenarios(), [load_scenario(n).mode for n in packaged_scenarios()])\n")
    out = _run(installed, code)
    assert out.strip() == "['hil', 'real', 'real_emulated', 'real_emulated_world', 'sim'] ['hil', 'real', 'real', 'real', 'sim']"
