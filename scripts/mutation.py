"""Mutation-test chosen modules with mutmut and print the mutation score per module.

    .venv/bin/python scripts/mutation.py                       # the default targets below
    .venv/bin/python scripts/mutation.py dexdrake/task.py      # one module, its default tests
    .venv/bin/python scripts/mutation.py hardware/allegro_can.py --tests tests/test_allegro_can.py
    .venv/bin/python scripts/mutation.py hardware/z1_udp.py --recheck --functions 'xǁOfficialZ1ǁ*'

Needs the `mutation` extra (`pip install -e '.[mutation]'`). Each module is mutated in its own
staging copy under `--workdir` (default `.mutation/`), laid out as the package is installed
(`hardware/` -> `dexdrake/hardware/`, ...) so the tests import the mutated file; only the test
files that cover the module run. Survivors can be inspected afterwards with
`cd .mutation/<module> && ../../.venv/bin/mutmut show <name>`; every verdict so far is kept in
`.mutation/<module>.verdicts.json` for `--recheck`. CPU-heavy: run it under `nice`.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import tomllib
from dataclasses import dataclass, field
from fnmatch import fnmatch
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent

# Source folder in the repository -> its place in the installed `dexdrake` package.
PACKAGE_DIRS = {"dexdrake": "dexdrake", "hardware": "dexdrake/hardware",
                "systems": "dexdrake/systems", "models": "dexdrake/models"}
ALSO_COPY = ["tests", "configs", "scripts", "README.md"]


@dataclass(frozen=True)
class Target:
    tests: list[str]  # test files or node ids: the only tests run against this module's mutants
    functions: list[str] = field(default_factory=lambda: ["*"])  # globs of the functions to mutate
    # CPU seconds of fixture set-up per run: mutmut times only the test calls, so without
    # this a mutant's run is cut short (and counted killed) while its fixtures are built
    setup_s: float = 1.0


# The feature maths' own tests (not the Drake-system and rerun ones, which call the same code).
DEXREP = ["tests/test_dexrep.py::" + t for t in (
    "test_occupancy_matches_brute_force", "test_fast_occupancy_applies_the_rule_of_occupancy_in_frame",
    "test_occupancy_cull_keeps_objects_at_the_grid_corner", "test_occupancy_order_is_x_major",
    "test_occupancy_of_a_half_space_is_decided_by_the_balls_alone_when_it_can",
    "test_occupancy_of_a_tilted_half_space_is_exact",
    "test_fast_occupancy_interpolates_only_the_voxels_the_balls_leave_open",
    "test_sdf_grid_interpolates_trilinearly_and_extrapolates_from_the_border_cell",
    "test_surface_on_sphere", "test_closest_points_match_analytic_sd", "test_local_geo_is_feature_of_nearest_sample",
    "test_hand_state_layout", "test_bad_meshes_are_refused", "test_cache_round_trip")]
LEARN = "tests/test_learn.py::"
CAN = "tests/test_allegro_can.py::"
TARGETS: dict[str, Target] = {
    "dexdrake/task.py": Target(["tests/test_task.py", "tests/test_task_boundaries.py"]),
    # the `geometries` fixture builds three SDF grids (about 10 CPU seconds; loaded from the
    # disk cache once built)
    "dexdrake/dexrep/occupancy.py": Target(DEXREP, setup_s=30.0),
    "dexdrake/dexrep/features.py": Target(DEXREP, setup_s=30.0),
    "dexdrake/dexrep/geometry.py": Target(DEXREP, ["xǁSdfGridǁ*", "xǁObjectGeometryǁ*"], setup_s=30.0),
    "dexdrake/objects/meshfile.py": Target(["tests/test_dexrep.py::test_bad_meshes_are_refused"], ["x_check_mesh*"]),
    "dexdrake/retarget/kinematics.py": Target(["tests/test_retarget.py::" + t for t in (
        "test_casadi_fk_matches_drake", "test_extract_tree_refuses_floating_base", "test_retarget_recovers_own_fk",
        "test_fk_holds_joints_outside_the_order_at_their_defaults", "test_fk_refuses_welds_unknown_joints_and_bodies")]),
    "dexdrake/learn/gae.py": Target([LEARN + "test_gae_hand_computed"]),
    # The maths; natural_gradient_step runs only inside DAPG training tests, too slow per mutant.
    "dexdrake/learn/npg.py": Target([LEARN + "test_cg_solves_spd_system",
                                     LEARN + "test_fisher_vector_product_matches_analytic",
                                     "tests/test_learn_maths.py"],
                                    ["x_flat_params*", "x_set_flat_params*", "x_flat_grad*", "x_conjugate_gradient*",
                                     "x_gaussian_kl*", "x_policy_kl*", "x_fisher_vector_product*"]),
    "dexdrake/learn/dapg.py": Target([LEARN + "test_demo_weight_and_seeds", "tests/test_learn_maths.py"],
                                     ["x_demo_weight*", "x_rollout_seeds*"]),
    "hardware/z1_udp.py": Target(["tests/test_z1_udp.py", "tests/test_z1_emulator.py", "tests/test_safety.py"]),
    "hardware/z1_emulator.py": Target(["tests/test_z1_emulator.py", "tests/test_z1_udp.py"]),
    "hardware/safety.py": Target(["tests/test_safety.py"]),
    # The CAN codec. The driver (its tests run in real time: a loaded machine fails them, so
    # run it on a quiet one) with
    #   --tests tests/test_allegro_can.py tests/test_allegro_driver_clock.py --functions
    #   'x_check_allegro_config*' 'x__model_limits*' 'xǁAllegroHandǁ*' 'x__array*' 'xǁ_Statsǁ*'
    "hardware/allegro_can.py": Target(
        [CAN + t for t in ("test_codec_round_trip", "test_ids_match_spec_table", "test_spec_real_frames",
                           "test_decode_rejects_with_specific_kind", "test_encode_rejects_bad_frames",
                           "test_decode_fuzz_only_raises_frame_error",
                           "test_default_limits_come_from_hand_description_in_bus_order")]
        + ["tests/test_allegro_codec_edges.py"],
        ["x_can_id*", "x__check_*", "x__int16x4*", "x__message*", "x_encode*", "x__split_id*", "x_decode*",
         "xǁFrameErrorǁ*", "x_default_joint_limits*"]),
}
KILLED = {1, 3, 24, -24, 36, 152, 255}  # mutmut exit codes of a killed mutant (failed or timed out)
TIMED_OUT = {24, -24, 36, 152}  # of those, the timeouts (CPU limit): --recheck runs them again


def module_prefix(module: str) -> str:
    """`hardware/allegro_can.py` -> `dexdrake.hardware.allegro_can.` (how mutmut names its mutants)."""
    return installed_path(module)[:-3].replace("/", ".") + "."


def installed_path(module: str) -> str:
    """`hardware/allegro_can.py` -> `dexdrake/hardware/allegro_can.py`."""
    top, _, rest = module.partition("/")
    if top not in PACKAGE_DIRS:
        raise SystemExit(f"mutation.py: error: {module} is not under {', '.join(PACKAGE_DIRS)}")
    return f"{PACKAGE_DIRS[top]}/{rest}"


def toml_value(value: object) -> str:
    """Strings, bools, numbers and lists of them as TOML (JSON's spelling is valid TOML here)."""
    return ("true" if value else "false") if isinstance(value, bool) else json.dumps(value)


def stage(module: str, tests: list[str], stage_dir: Path, setup_s: float = 1.0) -> None:
    """A fresh copy of the package and tests with a pyproject.toml that configures mutmut."""
    shutil.rmtree(stage_dir, ignore_errors=True)
    ignore = shutil.ignore_patterns("__pycache__", "*.pyc", "*.rrd")
    for src, dst in PACKAGE_DIRS.items():
        shutil.copytree(ROOT / src, stage_dir / dst, ignore=ignore, dirs_exist_ok=True)
    for name in ALSO_COPY:
        src = ROOT / name
        if src.is_dir():
            shutil.copytree(src, stage_dir / name, ignore=ignore)
        elif src.exists():
            shutil.copy2(src, stage_dir / name)
    pytest_options = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["pytest"]["ini_options"]
    mutmut_options = {
        "source_paths": ["dexdrake"],
        "only_mutate": [installed_path(module)],
        "also_copy": ALSO_COPY,
        "pytest_add_cli_args": ["-p", "no:cacheprovider", "-x"],
        "pytest_add_cli_args_test_selection": tests,
        "use_git_change_detection": False,
        "timeout_multiplier": 5.0,
        "timeout_constant": setup_s,
    }
    lines = ["[tool.mutmut]"] + [f"{k} = {toml_value(v)}" for k, v in mutmut_options.items()]
    lines += ["", "[tool.pytest.ini_options]"]
    lines += [f"{k} = {toml_value(v)}" for k, v in pytest_options.items()]
    (stage_dir / "pyproject.toml").write_text("\n".join(lines) + "\n")
    # Made now, so that Python's import cache does not record PYTHONPATH's folder as missing.
    (stage_dir / "mutants").mkdir()


def mutmut(stage_dir: Path, *args: str, log: Path | None = None) -> subprocess.CompletedProcess:
    """Run mutmut in `stage_dir`; its output is returned, or written to `log` as it comes."""
    # Subprocesses see the mutants too; one OpenMP thread keeps torch safe in mutmut's forks.
    env = dict(os.environ, PYTHONPATH=str(stage_dir / "mutants"), OMP_NUM_THREADS="1")
    cmd = [str(Path(sys.executable).with_name("mutmut")), *args]
    if log is None:
        return subprocess.run(cmd, cwd=stage_dir, env=env, text=True, capture_output=True)
    with log.open("w") as out:
        return subprocess.run(cmd, cwd=stage_dir, env=env, stdout=out, stderr=subprocess.STDOUT)


def verdicts(stage_dir: Path, module: str, functions: list[str]) -> dict[str, int | None]:
    """Exit code of each checked mutant of `module` in the chosen functions (None: not run)."""
    meta = json.loads((stage_dir / "mutants" / f"{installed_path(module)}.meta").read_text())
    return {name: code for name, code in meta["exit_code_by_key"].items()
            if any(fnmatch(name, module_prefix(module) + f) for f in functions)}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("modules", nargs="*", default=list(TARGETS),
                        help="repository paths of the modules to mutate (default: all targets)")
    parser.add_argument("--tests", nargs="+", help="test files to run (default: the module's own)")
    parser.add_argument("--workdir", type=Path, default=ROOT / ".mutation")
    parser.add_argument("--max-children", type=int, default=1, help="parallel test processes")
    parser.add_argument("--recheck", action="store_true",
                        help="re-run only the mutants the last run in --workdir left alive or timed out "
                             "(after adding tests, or giving more time)")
    parser.add_argument("--functions", nargs="+", metavar="GLOB",
                        help="only the mutants of these functions, as mutmut names them (e.g. "
                             "'x_encode*', 'xǁZ1Armǁstart*'; default: the module's); without --recheck "
                             "they are run afresh and the module's other verdicts are kept")
    args = parser.parse_args(argv)
    rows = []
    for module in args.modules:
        target = TARGETS.get(module) or Target(args.tests or [])
        tests = args.tests or target.tests
        if not tests:
            parser.error(f"no default tests for {module}; pass --tests")
        stage_dir = args.workdir / Path(module).with_suffix("").as_posix().replace("/", "_")
        functions = args.functions or target.functions
        names = [module_prefix(module) + f for f in functions]
        before: dict[str, int | None] = {}
        # every verdict so far (a recheck's mutmut run holds only its own); beside the staging
        # copy, which each run replaces, so that a failed run loses none
        saved = stage_dir.with_name(stage_dir.name + ".verdicts.json")
        if args.recheck:  # killed mutants stay killed when tests are only added: re-run the others
            if not saved.exists():
                parser.error(f"--recheck: no earlier run of {module} in {args.workdir}")
            before = json.loads(saved.read_text())
            names = [name for name, code in before.items()
                     if (code not in KILLED or code in TIMED_OUT) and any(fnmatch(name, pattern) for pattern in names)]
        elif args.functions and saved.exists():  # these functions afresh (their code changed), the rest kept
            before = {name: code for name, code in json.loads(saved.read_text()).items()
                      if not any(fnmatch(name, pattern) for pattern in names)}
        stage(module, tests, stage_dir, target.setup_s)
        log = stage_dir / "mutmut-run.log"
        if names:
            mutmut(stage_dir, "run", "--max-children", str(args.max_children), *names, log=log)
            if not (stage_dir / "mutants" / "mutmut-stats.json").exists():
                print(f"{module}: mutmut failed, see {log}", file=sys.stderr)
                return 1
        rerun = verdicts(stage_dir, module, functions) if names else dict(before)
        if args.recheck:  # mutants of code since removed are dropped
            codes = {n: c for n, c in before.items() if n in rerun} | {n: rerun[n] for n in names if n in rerun}
        else:
            codes = before | rerun
        saved.write_text(json.dumps(codes, indent=0))
        killed = sum(code in KILLED for code in codes.values())
        rows.append((module, killed, len(codes)))
        timed_out = sum(code in TIMED_OUT for code in codes.values())
        print(f"{module}: {killed}/{len(codes)} killed = {100 * killed / max(len(codes), 1):.1f} % "
              f"({timed_out} of them by timeout)", flush=True)
        for name, code in codes.items():
            if code not in KILLED:
                print(f"    alive ({'no tests' if code in (5, 33) else code}): {name}")
    print("\nmodule | killed | mutants | score")
    for module, killed, tested in rows:
        print(f"{module} | {killed} | {tested} | {100 * killed / max(tested, 1):.1f} %")
    return 0


if __name__ == "__main__":
    sys.exit(main())
