"""A training recipe: the typed settings of every stage of `dexdrake train recipe`.

A recipe is a YAML mapping read into the `Recipe` dataclass tree: augment (optional) ->
expert table -> DAgger -> DAPG stages -> choice of iterate on validation seeds -> test
evaluation -> ship, every env seeing the object pose through the recipe's `perception` model. Each stage's training settings are the training code's own config
dataclasses (`dagger.DaggerConfig`, `dapg.DAPGConfig`); the recipe adds only what those
configs leave to the command line (objects, episodes_per_object, horizon). Unknown keys,
wrong types, renamed keys (`RENAMED`) and fields the pipeline derives itself are refused in
one line naming the field.

The recipe's identity is the sha256 of its canonical JSON (`recipe_sha256`), so comments
and formatting do not change it; `changed_fields` names the dotted fields two recipes
differ in (`dagger.config.epochs`, `dapg.1.config.lam0`, ...).
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import types
import typing
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import yaml

from dexdrake import argtypes
from dexdrake.errors import DexdrakeError
from dexdrake.eval.evaluate import EVAL_HORIZON
from dexdrake.learn.dagger import DaggerConfig
from dexdrake.learn.dapg import DAPGConfig
from dexdrake.perceived_pose import PerceptionModel


TRAINING_OBJECTS_HELP = ("'train', 'train+augmented' (with the scaled copies and shapes of `dexdrake objects "
                         "augment`) or comma-separated object names")


@dataclass(frozen=True)
class Augment:
    """Scaled copies of each training object and procedural shapes (`dexdrake objects augment`)."""

    copies: int = 4
    shapes: int = 0


@dataclass(frozen=True)
class ExpertStage:
    """The expert alone on every DAgger training object: its success per object (training seeds)."""

    episodes_per_object: int = 5
    horizon: int = EVAL_HORIZON


@dataclass(frozen=True)
class DaggerStage:
    """DAgger from the expert on `objects` (a training spec: 'train', 'train+augmented' or names)."""

    objects: str = field(default="train", metadata={"help": TRAINING_OBJECTS_HELP})
    config: DaggerConfig = DaggerConfig()


@dataclass(frozen=True)
class DapgStage:
    """DAPG from the previous stage's policy (DAgger's chosen one, or the previous DAPG stage's
    best), with the DAgger data as its demonstration term (`demo_pairs` of them, seeded)."""

    objects: str = field(default="train", metadata={"help": TRAINING_OBJECTS_HELP})
    episodes_per_object: int = field(default=10, metadata={
        "type": argtypes.episodes, "metavar": "N", "help": argtypes.episodes_per_object_help("each iteration")})
    horizon: int = 100  # control steps per trajectory
    demo_pairs: int = field(default=50000, metadata={
        "flag": "demo-samples", "type": argtypes.count,
        "help": "demonstration pairs kept (uniform, seeded), all used every iteration"})
    config: DAPGConfig = DAPGConfig()


@dataclass(frozen=True)
class ChooseStage:
    """The candidate iterates of the last training stage (every DAPG checkpoint and its last
    policy; DAgger's iterates without DAPG) evaluated on `objects` at the validation seeds;
    the highest average success is chosen (ties: the later iterate)."""

    objects: str = "seen"
    episodes_per_object: int = 5
    horizon: int = EVAL_HORIZON


@dataclass(frozen=True)
class TestStage:
    """The chosen policy on the seen and unseen objects at the test seeds (the shipped tables)."""

    seen: str = "seen"
    unseen: str = "unseen"
    episodes_per_object: int = 10
    horizon: int = EVAL_HORIZON


@dataclass(frozen=True)
class Ship:
    """Names in the weights folder: NAME.pt/.json, TABLES_seen.md/_unseen.md, NAME_<stage>.csv/.png."""

    name: str = ""  # default: <hand>_dexrep_policy
    tables: str = ""  # default: eval_<hand>


@dataclass(frozen=True)
class Recipe:
    dagger: DaggerStage = DaggerStage()
    dapg: tuple[DapgStage, ...] = ()
    expert: ExpertStage = ExpertStage()
    choose: ChooseStage = ChooseStage()
    test: TestStage = TestStage()
    augment: Augment | None = None
    ship: Ship = Ship()
    # how the features see the object pose in every training and evaluation env (the
    # deployed scenario's: dexdrake/perceived_pose.py); default the true pose
    perception: PerceptionModel = PerceptionModel()
    description: str = ""

    @property
    def hand(self) -> str:
        return self.dagger.config.hand

    @property
    def policy_name(self) -> str:
        return self.ship.name or f"{self.hand}_dexrep_policy"

    @property
    def tables_name(self) -> str:
        return self.ship.tables or f"eval_{self.hand}"


# Fields the pipeline sets itself: the command line's workers and backend, the DAgger start
# (from the expert, no prior runs), and DAPG's batch shape from the stage's objects and horizon.
DERIVED = {
    DaggerConfig: {"workers": "--workers", "backend": "--backend", "init": "the expert", "prior": "the expert"},
    DAPGConfig: {"rollouts_per_iteration": "episodes_per_object x objects", "seed_groups": "objects",
                 "time_scale": "horizon", "progress": "the command"},
}


# Keys a recipe once used: refused in one line that names the key now.
RENAMED = {DapgStage: {"per_object": "episodes_per_object"}, ChooseStage: {"episodes": "episodes_per_object"},
           TestStage: {"episodes": "episodes_per_object"}}


def _typed(tp: Any, value: Any, where: str) -> Any:
    """`value` (from YAML) as type `tp`; DexdrakeError naming `where` otherwise."""
    origin, args = typing.get_origin(tp), typing.get_args(tp)
    if origin in (typing.Union, types.UnionType):
        if value is None and type(None) in args:
            return None
        (inner,) = [a for a in args if a is not type(None)]
        return _typed(inner, value, where)
    if dataclasses.is_dataclass(tp):
        return from_dict(tp, value, where)
    if origin is tuple:
        if not isinstance(value, list):
            raise DexdrakeError(f"recipe field {where}: expected a list, got {value!r}")
        return tuple(_typed(args[0], v, f"{where}.{i}") for i, v in enumerate(value))
    if tp is float and isinstance(value, int) and not isinstance(value, bool):
        return float(value)
    if not isinstance(value, tp) or (tp is int and isinstance(value, bool)):
        raise DexdrakeError(f"recipe field {where}: expected {tp.__name__}, got {value!r}")
    return value


def from_dict(cls: type, data: Any, where: str = "") -> Any:
    """An instance of dataclass `cls` from a mapping; refuses unknown, mistyped or derived fields."""
    name = where or "recipe"
    if not isinstance(data, dict):
        raise DexdrakeError(f"recipe field {name}: expected a mapping, got {data!r}")
    hints = typing.get_type_hints(cls)
    known = {f.name for f in dataclasses.fields(cls)}
    prefix = f"{where}." if where else ""
    for key in data:
        if key in RENAMED.get(cls, {}):
            raise DexdrakeError(f"recipe field {prefix}{key} is now {prefix}{RENAMED[cls][key]}")
        if key not in known:
            raise DexdrakeError(f"recipe field {prefix}{key} is unknown; {name} has {sorted(known)}")
        if key in DERIVED.get(cls, {}):
            raise DexdrakeError(f"recipe field {prefix}{key} is set by the pipeline ({DERIVED[cls][key]}), "
                                "not by a recipe")
    return cls(**{k: _typed(hints[k], v, f"{prefix}{k}") for k, v in data.items()})


def load_recipe(path: str | Path) -> Recipe:
    """The recipe in YAML file `path`, checked (types, names of hand, feature set, reward)."""
    path = Path(path)
    try:
        data = yaml.safe_load(path.read_text())
    except OSError as exc:
        raise DexdrakeError(f"cannot read recipe {path}: {exc.strerror}") from exc
    except yaml.YAMLError as exc:
        raise DexdrakeError(f"recipe {path} is not valid YAML: {str(exc).splitlines()[0]}") from exc
    recipe = from_dict(Recipe, data or {})
    check_recipe(recipe)
    return recipe


def check_recipe(recipe: Recipe) -> None:
    """Refuse names and counts no stage could run with (before any work)."""
    from dexdrake.dexrep.feature_sets import FEATURE_SETS
    from dexdrake.hands.action_map import ActionMap
    from dexdrake.hands.description import hand_names, load_hand
    from dexdrake.task import TARGET_THRESHOLDS

    config = recipe.dagger.config
    if config.hand not in hand_names():
        raise DexdrakeError(f"recipe field dagger.config.hand: {config.hand!r} is not one of {hand_names()}")
    if config.feature_set not in FEATURE_SETS:
        raise DexdrakeError(f"recipe field dagger.config.feature_set: {config.feature_set!r} is not one of "
                            f"{list(FEATURE_SETS)}")
    try:
        ActionMap(load_hand(config.hand), config.arm_action)
    except DexdrakeError as err:
        raise DexdrakeError(f"recipe field dagger.config.arm_action: {err}") from None
    counts = {"expert.episodes_per_object": recipe.expert.episodes_per_object, "expert.horizon": recipe.expert.horizon,
              "dagger.config.iterations": config.iterations,
              "choose.episodes_per_object": recipe.choose.episodes_per_object, "choose.horizon": recipe.choose.horizon,
              "test.episodes_per_object": recipe.test.episodes_per_object, "test.horizon": recipe.test.horizon}
    for k, stage in enumerate(recipe.dapg):
        counts |= {f"dapg.{k}.episodes_per_object": stage.episodes_per_object, f"dapg.{k}.horizon": stage.horizon,
                   f"dapg.{k}.demo_pairs": stage.demo_pairs, f"dapg.{k}.config.iterations": stage.config.iterations}
        if stage.config.reward not in TARGET_THRESHOLDS:
            raise DexdrakeError(f"recipe field dapg.{k}.config.reward: {stage.config.reward!r} is not one of "
                                f"{sorted(TARGET_THRESHOLDS)}")
    for name, value in counts.items():
        if value < 1:
            raise DexdrakeError(f"recipe field {name}: need >= 1, got {value}")
    check_objects(recipe)


def check_objects(recipe: Recipe) -> None:
    """Refuse object selections that name no object, or held-out ones for training (the
    augmented split is checked when it is made, by the augment stage)."""
    from dexdrake.objects.library import resolve_objects, training_objects

    specs = [("dagger.objects", recipe.dagger.objects, training_objects),
             *((f"dapg.{k}.objects", s.objects, training_objects) for k, s in enumerate(recipe.dapg)),
             ("choose.objects", recipe.choose.objects, resolve_objects),
             ("test.seen", recipe.test.seen, resolve_objects), ("test.unseen", recipe.test.unseen, resolve_objects)]
    for where, spec, check in specs:
        if recipe.augment is not None and "augmented" in spec:
            continue
        try:
            check(spec)
        except DexdrakeError as exc:
            raise DexdrakeError(f"recipe field {where}: {exc}") from exc


def recipe_dict(recipe: Recipe) -> dict[str, Any]:
    """The recipe as plain JSON data (tuples as lists), without the fields the pipeline derives."""
    data = json.loads(json.dumps(asdict(recipe)))
    for config, cls in [(data["dagger"]["config"], DaggerConfig), *((s["config"], DAPGConfig) for s in data["dapg"])]:
        for key in DERIVED[cls]:
            del config[key]
    return data


def recipe_sha256(recipe: Recipe) -> str:
    """sha256 of the recipe's canonical JSON (sorted keys): its identity, whatever its YAML layout."""
    return hashlib.sha256(json.dumps(recipe_dict(recipe), sort_keys=True).encode()).hexdigest()


def changed_fields(old: Any, new: Any, where: str = "") -> list[tuple[str, Any, Any]]:
    """(dotted field, old value, new value) for every leaf where two recipe dicts differ; a
    list item present on one side only is one entry (the other side None)."""
    if isinstance(old, dict) and isinstance(new, dict):
        keys = list(old) + [k for k in new if k not in old]
        return [c for k in keys for c in changed_fields(old.get(k), new.get(k), f"{where}.{k}" if where else k)]
    if isinstance(old, list) and isinstance(new, list):
        out = [c for i, (a, b) in enumerate(zip(old, new)) for c in changed_fields(a, b, f"{where}.{i}")]
        longer = old if len(old) > len(new) else new
        return out + [(f"{where}.{i}", old[i] if i < len(old) else None, new[i] if i < len(new) else None)
                      for i in range(min(len(old), len(new)), len(longer))]
    return [] if old == new else [(where, old, new)]


@dataclass(frozen=True)
class StagePlan:
    """A stage of the pipeline: its folder name and the recipe fields (dotted prefixes) it reads."""

    name: str
    reads: tuple[str, ...] = ()


def stage_plan(recipe: Recipe) -> list[StagePlan]:
    """The stages in order. A stage reads its own section and what shapes its input: the
    expert runs on DAgger's hand and objects; the choice of iterate on the last DAPG stage."""
    plan = [StagePlan("augment", ("augment",))] if recipe.augment else []
    plan += [StagePlan("expert", ("expert", "dagger.objects", "dagger.config.hand")),
             StagePlan("dagger", ("dagger", "perception"))]
    plan += [StagePlan(f"dapg{k + 1}", (f"dapg.{k}", "perception")) for k in range(len(recipe.dapg))]
    return plan + [StagePlan("choose", ("choose", "dapg", "perception")), StagePlan("test", ("test", "perception"))]


def reads(stage: StagePlan, dotted: str) -> bool:
    """True when field `dotted` lies in (or contains) one of the stage's prefixes."""
    return any(dotted == p or dotted.startswith(p + ".") or p.startswith(dotted + ".") for p in stage.reads)
