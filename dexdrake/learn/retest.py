"""`dexdrake train retest`: re-evaluate a shipped policy with the current code.

The policy NAME.pt must lie beside its manifest NAME.json, whose sha256 it must match. It
is evaluated on the test seeds as its tables were made: the recipe's test objects, horizon
and episodes per object (a policy shipped before recipes: the library's seen and unseen
objects, the horizon and episodes its metrics record). The seen/unseen tables beside it
(the recipe's `ship.tables`; for a policy shipped before recipes eval_seen.md for the Adroit
hand, eval_<hand>_seen.md for others) and the manifest's `metrics` are rewritten; the
training record is kept and the command is appended to `commands`, replacing an earlier
re-evaluation's commands.
"""

from __future__ import annotations

import json
import tempfile
from collections.abc import Callable
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

from dexdrake.errors import DexdrakeError
from dexdrake.learn.env_protocol import EnvFactory
from dexdrake.learn.pipeline import evaluate_test
from dexdrake.learn.recipe import Recipe, TestStage, from_dict
from dexdrake.learn.ship import sha256, ship_test_tables
from dexdrake.objects.meshfile import write_atomic
from dexdrake.outputs import check_writable

# Commands of an earlier re-evaluation in a manifest (this command's, and the evaluations that
# made a shipped policy's tables): replaced by this one's.
RETEST_COMMANDS = ("dexdrake train retest ", "dexdrake eval ")


@dataclass(frozen=True)
class Shipped:
    """A shipped policy, its manifest and how its test tables were made."""

    policy: Path
    manifest: dict[str, Any]
    test: TestStage
    tables: Path  # the seen/unseen tables' path without _seen.md / _unseen.md
    scenario: dict[str, Any]  # the scenario record of its checkpoint (learn.policy.load_policy)

    @property
    def manifest_path(self) -> Path:
        return self.policy.with_suffix(".json")


def read_shipped(policy: Path) -> Shipped:
    """The shipped `policy` and its manifest; refused in one line unless the policy loads and
    the manifest lies beside it and records its sha256."""
    from dexdrake.learn.policy import load_policy

    scenario = load_policy(policy)[1]["scenario"]
    path = policy.with_suffix(".json")
    if not path.is_file():
        raise DexdrakeError(f"{policy} has no manifest {path.name} beside it: only a shipped policy is re-tested")
    try:
        manifest = json.loads(path.read_text())
        recorded, hand, metrics = manifest["sha256"], manifest["hand"], manifest["metrics"]
    except (json.JSONDecodeError, KeyError, TypeError) as exc:
        raise DexdrakeError(f"{path} is not a shipped policy's manifest ({type(exc).__name__}: {exc})") from None
    if recorded != sha256(policy):
        raise DexdrakeError(f"{policy} is not the file its manifest {path.name} records (sha256 {sha256(policy)[:12]}, "
                            f"recorded {str(recorded)[:12]}): re-test the shipped file as it was shipped")
    if "recipe" in manifest:
        try:
            recipe = from_dict(Recipe, manifest["recipe"]["settings"])
        except DexdrakeError as exc:
            raise DexdrakeError(f"{path}: its recipe does not load: {exc}") from None
        return Shipped(policy, manifest, recipe.test, policy.with_name(recipe.tables_name), scenario)
    seen = metrics["seen"]
    tables = "eval" if hand == "adroit" else f"eval_{hand}"
    return Shipped(policy, manifest, TestStage("seen", "unseen", seen["episodes_per_object"], seen["horizon"]),
                   policy.with_name(tables), scenario)


def retest(shipped: Shipped, env_for_policy: Callable[..., EnvFactory], workers: int, command: str,
           episodes_per_object: int | None = None, envs_per_worker: int = 1, progress: bool = True) -> dict[str, Any]:
    """Evaluate `shipped` on the test seeds (`episodes_per_object`, default as its tables were
    made), rewrite its tables and its manifest's metrics, append `command` to the manifest's
    commands; returns the metrics. A folder that cannot be written is refused before any episode."""
    check_writable(shipped.manifest_path.parent, folder=True)
    test = shipped.test if episodes_per_object is None else replace(shipped.test,
                                                                    episodes_per_object=episodes_per_object)
    with tempfile.TemporaryDirectory(prefix="retest_") as work:
        evaluate_test(shipped.policy, test, Path(work), env_for_policy, workers, command, progress, envs_per_worker)
        metrics = ship_test_tables(Path(work), shipped.policy, shipped.tables, shipped.manifest["policy"])
    manifest = dict(shipped.manifest)
    kept = [c for c in manifest["commands"] if not c["command"].startswith(RETEST_COMMANDS)]
    note = "re-evaluated the shipped policy on the test seeds; wrote its tables and metrics"
    manifest.update(commands=kept + [{"command": command, "note": note}], metrics=metrics)
    write_atomic(shipped.manifest_path, (json.dumps(manifest, indent=1) + "\n").encode())
    return metrics
