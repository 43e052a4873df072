"""Mutation-test chosen modules with mutmut and print the mutation score per module.

    .venv/bin/python scripts/mutation.py                       # the default targets below
    .venv/bin/python scripts/mutation.py dexdrake/task.py      # one module, its default tests
    .venv/bin/python scripts/mutation.py hardware/allegro_can.py --tests tests/test_allegro_can.py

Needs the `mutation` extra (`pip install -e '.[mutation]'`). Each module is mutated in its own
staging copy under `--workdir` (default `.mutation/`), laid out as the package is installed
(`hardware/` -> `dexdrake/hardware/`, ...) so the tests import the mutated file; only the test
files that cover the module run. Survivors can be inspected afterwards with
`cd .mutation/<module> && ../../.venv/bin/mutmut show <name>`. CPU-heavy: run it under `nice`.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import tomllib
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent

# Source folder in the repository -> its place in the installed `dexdrake` package.
PACKAGE_DIRS = {"dexdrake": "dexdrake", "hardware": "dexdrake/hardware",
                "systems": "dexdrake/systems", "models": "dexdrake/models"}
ALSO_COPY = ["tests", "configs", "scripts", "README.md"]

# Module -> the test files that cover it (the only tests run against its mutants).
TARGETS: dict[str, list[str]] = {
    "dexdrake/task.py": ["tests/test_task.py", "tests/test_task_boundaries.py"],
    "dexdrake/dexrep/occupancy.py": ["tests/test_dexrep.py"],
    "dexdrake/dexrep/features.py": ["tests/test_dexrep.py"],
    "dexdrake/dexrep/geometry.py": ["tests/test_dexrep.py"],
    "dexdrake/retarget/kinematics.py": ["tests/test_retarget.py"],
    "dexdrake/learn/gae.py": ["tests/test_learn.py"],
    "dexdrake/learn/npg.py": ["tests/test_learn.py"],
    "dexdrake/learn/dapg.py": ["tests/test_learn.py"],
    "hardware/allegro_can.py": ["tests/test_allegro_can.py"],
}


def installed_path(module: str) -> str:
    """`hardware/allegro_can.py` -> `dexdrake/hardware/allegro_can.py`."""
    top, _, rest = module.partition("/")
    if top not in PACKAGE_DIRS:
        raise SystemExit(f"mutation.py: error: {module} is not under {', '.join(PACKAGE_DIRS)}")
    return f"{PACKAGE_DIRS[top]}/{rest}"


def toml_value(value: object) -> str:
    """Strings, bools, numbers and lists of them as TOML (JSON's spelling is valid TOML here)."""
    return ("true" if value else "false") if isinstance(value, bool) else json.dumps(value)


def stage(module: str, tests: list[str], stage_dir: Path) -> None:
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


def score(stage_dir: Path) -> tuple[dict[str, int], list[str]]:
    """Counts per verdict and the names of the mutants that no test killed."""
    mutmut(stage_dir, "export-cicd-stats")
    stats = json.loads((stage_dir / "mutants" / "mutmut-cicd-stats.json").read_text())
    listing = mutmut(stage_dir, "results").stdout
    alive = [line.split(":")[0].strip() for line in listing.splitlines()
             if line.strip().endswith(("survived", "no tests"))]
    return stats, alive


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("modules", nargs="*", default=list(TARGETS),
                        help="repository paths of the modules to mutate (default: all targets)")
    parser.add_argument("--tests", nargs="+", help="test files to run (default: the module's own)")
    parser.add_argument("--workdir", type=Path, default=ROOT / ".mutation")
    parser.add_argument("--max-children", type=int, default=1, help="parallel test processes")
    args = parser.parse_args(argv)
    rows = []
    for module in args.modules:
        tests = args.tests or TARGETS.get(module)
        if not tests:
            parser.error(f"no default tests for {module}; pass --tests")
        stage_dir = args.workdir / Path(module).with_suffix("").as_posix().replace("/", "_")
        stage(module, tests, stage_dir)
        run = mutmut(stage_dir, "run", "--max-children", str(args.max_children), log=stage_dir / "mutmut-run.log")
        if not (stage_dir / "mutants" / "mutmut-stats.json").exists() and run.returncode:
            print(f"{module}: mutmut failed, see {stage_dir / 'mutmut-run.log'}", file=sys.stderr)
            return 1
        stats, alive = score(stage_dir)
        tested = stats["total"] - stats.get("skipped", 0)
        killed = stats.get("killed", 0) + stats.get("timeout", 0)
        rows.append((module, killed, tested))
        print(f"{module}: {killed}/{tested} killed = {100 * killed / max(tested, 1):.1f} %", flush=True)
        for name in alive:
            print(f"    alive: {name}")
    print("\nmodule | killed | mutants | score")
    for module, killed, tested in rows:
        print(f"{module} | {killed} | {tested} | {100 * killed / max(tested, 1):.1f} %")
    return 0


if __name__ == "__main__":
    sys.exit(main())
