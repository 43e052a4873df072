"""A grasp controller alone (the grasp expert or the scripted grasp): its success per object,
and the choice of the expert's grasp variant per object by simulated trials.

`controller_table` runs a controller (`make(env)` after each reset, then `controller(env)
-> joint set-points` every control step) for seeds S..S+N-1 on every object, one episode per
sampler job (the one episode loop, dexdrake/episode.py), and times its calls in CPU time:
`ControllerTable` holds the episodes and writes them as a markdown table (objects, then
categories, then overall) with a CSV beside it.

`choose_variants` tries the expert's grasp variants (`VARIANTS`: overrides of the hand's
GraspScript) on each object for the given seeds, one object per sampler job; the variant
with the most successes, less its handicap (`HANDICAPS`: the grasps a cloned policy imitates
poorly), wins (ties: the earlier one, the hand's default first). A variant stops trying seeds
once it can no longer beat the best so far (`best_variant`), which chooses exactly as trying
every seed would. The result is the expert's grasp table
(`<hand>_expert_grasps.json`, read by systems/reactive_grasp.py).

The envs, the controllers and the expert of a variant come from the caller (the command
line), so the core never imports the Drake systems.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from functools import partial
from pathlib import Path
from typing import Any

from dexdrake.episode import EpisodeResult
from dexdrake.errors import DexdrakeError
from dexdrake.eval.evaluate import pool_by_category
from dexdrake.eval.tables import fault_lines
from dexdrake.hands.description import HandDescription
from dexdrake.learn.samplers import Sampler
from dexdrake.objects.meshfile import write_atomic

MakeController = Callable[[Any], Callable[[Any], Any]]
"""env -> the controller of its current episode, called with the env every control step and
returning joint set-points. Picklable (sampler workers call it)."""

_PINCH: dict[str, Any] = {"closed_pose": "pinch", "open_pose": "pinch_open", "min_height": 0.07, "palm_depth": -0.04,
                          "tall_palm_depth": -0.04, "reach": -0.033, "side": -0.035, "hover": 0.12,
                          "closed_hold": 1.1}  # the 'pinch' variant (see VARIANTS)
VARIANTS: dict[str, dict[str, Any]] = {  # name -> GraspScript overrides; the first is the hand's default
    "power": {},
    "power_80": {"closure": 0.8},
    "oppose_80": {"closed_pose": "oppose", "closure": 0.8},
    "oppose_70": {"closed_pose": "oppose", "closure": 0.7},
    "power_floor_10": {"min_height": 0.01},  # flat objects: the grasp centre 1 cm above the table, ...
    "power_floor_25": {"min_height": 0.025},  # ... or 2.5 cm (the default plans it below the table)
    "oppose_80_floor_10": {"closed_pose": "oppose", "closure": 0.8, "min_height": 0.01},
    "oppose_80_floor_25": {"closed_pose": "oppose", "closure": 0.8, "min_height": 0.025},
    # flat and hollow objects: the thumb pre-shaped to oppose before the descent, the grasp centre
    # 1.5 cm below the top (a fingertip pinch; a rim pinch on a deep bowl) or 7 cm (a stem)
    "pinch_15": {"closed_pose": "oppose", "open_pose": "oppose", "palm_depth": 0.015, "tall_palm_depth": 0.015},
    "pinch_15_reach_40_80": {"closed_pose": "oppose", "open_pose": "oppose", "closure": 0.8, "palm_depth": 0.015,
                             "tall_palm_depth": 0.015, "reach": -0.04},
    "stem_70": {"closed_pose": "oppose", "open_pose": "oppose", "closure": 0.8, "palm_depth": 0.07,
                "tall_palm_depth": 0.07, "reach": -0.04},
    # wide and tall objects: the palm down on the top (the grasp centre 5 cm below it), or a
    # deeper grasp around the body with the fingers closing 80 %
    "palm_50": {"palm_depth": 0.05, "tall_palm_depth": 0.05},
    "palm_65_80": {"palm_depth": 0.065, "tall_palm_depth": 0.065, "closure": 0.8},
    # low, lying and pointed objects: the grasp centre at the top (the fingers wrap the upper half, the
    # palm clear of the table and of a wide base), 5 cm back from the object's centre instead of 3 (the
    # thumb meets the near side as the fingers reach the far one), or both
    "palm_0": {"palm_depth": 0.0, "tall_palm_depth": 0.0},
    "back_50": {"reach": -0.05},
    "palm_0_back_50": {"palm_depth": 0.0, "tall_palm_depth": 0.0, "reach": -0.05},
    # wide dishes: the same pinch on the rim, 6 cm out along the fingers, 1.5 or 0.8 cm below the top
    "rim_60": {"closed_pose": "oppose", "open_pose": "oppose", "palm_depth": 0.015, "tall_palm_depth": 0.015,
               "reach": 0.06},
    "rim_60_low": {"closed_pose": "oppose", "open_pose": "oppose", "palm_depth": 0.008, "tall_palm_depth": 0.008,
                   "reach": 0.06},
    # flat, thin and hollow objects (hands with 'pinch' poses): fingertips pointed down close toward the
    # thumb at table level (the grasp centre 7 cm above the table, or 4 cm above a taller top, 3.5 cm toward
    # the little-finger side to centre the tips), holding only once the thumb and a finger touch; across the
    # footprint's centre, or on the rim 2 cm inside its far edge (plates, bowls, rings)
    "pinch": _PINCH,
    "pinch_rim": {**_PINCH, "reach": -0.02, "reach_edge": 1.0},
    # the pinch lifted slowly (its arm lead 0.02: a fast lift shakes a pinched knife out), or closed
    # firmer (hands with a 'pinch_firm' pose: the pinch's fingers and thumb further past contact) 5 mm lower
    "pinch_slow": {**_PINCH, "lift_lead": 0.02},
    "pinch_firm": {**_PINCH, "closed_pose": "pinch_firm", "min_height": 0.065, "palm_depth": -0.035,
                   "tall_palm_depth": -0.035, "lift_lead": 0.06},
}
# Successes a variant gives up in the choice: a fingertip pinch must win by more than these
# over every whole-hand grasp, for a policy cloned from the expert imitates pinches far worse.
HANDICAPS: dict[str, int] = {"pinch": 2, "pinch_rim": 2, "pinch_slow": 2, "pinch_firm": 2}


# ------------------------------------------------------------------------ per-object table
@dataclass
class ControllerEpisode:
    """One episode of a controller alone, with the CPU time its calls took."""

    result: EpisodeResult
    cpu_s: float  # CPU time of the controller's calls (its construction after the reset excluded)
    calls: int


def controller_episode(make: MakeController, env: Any, policy: None, job: tuple[str, int]) -> ControllerEpisode:
    """One episode (job = (object, seed)) of the controller `make` builds, by `env.rollout`,
    its calls timed; a sampler Episode with `make` bound first."""
    name, seed = job
    cpu, calls = 0.0, 0

    def timed(env: Any) -> Callable[[Any], Any]:
        env.fingertip_distances()  # the first query loads the object's geometry: here, outside the timed calls
        controller = make(env)

        def call(env: Any) -> Any:
            nonlocal cpu, calls
            start = time.process_time()
            q = controller(env)
            cpu, calls = cpu + time.process_time() - start, calls + 1
            return q

        return call

    result = env.rollout(timed, seed, object_name=name)
    return ControllerEpisode(result, cpu, calls)


def _pct(wins: int, runs: int) -> float:
    return 100.0 * wins / runs


@dataclass
class ControllerTable:
    """The episodes of one controller alone on each object (seeds first_seed .. + episodes_per_object - 1)."""

    objects: list[str]
    first_seed: int
    episodes_per_object: int
    horizon: int
    categories: dict[str, str]  # object -> its category
    episodes: dict[str, list[ControllerEpisode]] = field(default_factory=dict)  # object -> its episodes, seed order
    wall_s: float = 0.0

    def seeds_text(self) -> str:
        return f"{self.first_seed}..{self.first_seed + self.episodes_per_object - 1}"

    def object_rows(self) -> list[dict[str, Any]]:
        """Per object: category, successes, episodes, success %, mean max lift (m), CPU ms per controller call."""
        rows = []
        for name in self.objects:
            eps = self.episodes[name]
            wins, lifts = sum(e.result.success for e in eps), [e.result.max_lift for e in eps]
            rows.append({"object": name, "category": self.categories[name], "successes": wins, "episodes": len(eps),
                         "success_pct": _pct(wins, len(eps)), "mean_max_lift_m": sum(lifts) / len(lifts),
                         "ms_per_call": 1e3 * sum(e.cpu_s for e in eps) / max(sum(e.calls for e in eps), 1)})
        return rows

    def category_rows(self) -> list[dict[str, Any]]:
        """Per category (sorted): successes, episodes, success %."""
        pooled = pool_by_category((r["object"], r["category"], r["successes"], r["episodes"]) for r in self.object_rows())
        return [{"category": c, "successes": w, "episodes": n, "success_pct": _pct(w, n)}
                for c, (_, w, n) in pooled.items()]

    def success_pct(self) -> float:
        """Success % over every episode."""
        rows = self.object_rows()
        return _pct(sum(r["successes"] for r in rows), sum(r["episodes"] for r in rows))

    def markdown(self, heading: str, notes: Sequence[str]) -> str:
        """`heading`, the paragraphs `notes`, the episodes a fault ended, the object table, the
        category table and the overall line."""
        objects, categories = self.object_rows(), self.category_rows()
        wins, runs = sum(r["successes"] for r in objects), sum(r["episodes"] for r in objects)
        worst = min(r["success_pct"] for r in categories)
        mean_ms = sum(r["ms_per_call"] for r in objects) / len(objects)
        lines = [f"# {heading}", ""]
        for note in notes:
            lines += [note, ""]
        faults = fault_lines([e.result for episodes in self.episodes.values() for e in episodes])
        lines += [*faults, ""] if faults else []
        lines += ["| object | category | success | rate | mean max lift (m) | ms |", "|---|---|---|---|---|---|"]
        lines += [f"| {r['object']} | {r['category']} | {r['successes']}/{r['episodes']} | {r['success_pct']:.0f} % "
                  f"| {r['mean_max_lift_m']:.3f} | {r['ms_per_call']:.2f} |" for r in objects]
        lines += ["", "| category | success | rate |", "|---|---|---|"]
        lines += [f"| {r['category']} | {r['successes']}/{r['episodes']} | {r['success_pct']:.0f} % |" for r in categories]
        lines += ["", f"**Overall: {wins}/{runs} = {_pct(wins, runs):.1f} %; worst category {worst:.0f} %; "
                      f"{mean_ms:.2f} ms per controller call (mean over objects)**", ""]
        return "\n".join(lines)

    def csv(self) -> str:
        """One row per object, then one per category."""
        lines = ["kind,name,category,successes,episodes,success_pct,mean_max_lift_m,ms_per_call"]
        lines += [f"object,{r['object']},{r['category']},{r['successes']},{r['episodes']},{r['success_pct']:.1f},"
                  f"{r['mean_max_lift_m']:.4f},{r['ms_per_call']:.3f}" for r in self.object_rows()]
        lines += [f"category,,{r['category']},{r['successes']},{r['episodes']},{r['success_pct']:.1f},,"
                  for r in self.category_rows()]
        return "\n".join(lines) + "\n"

    def write(self, md_path: Path, heading: str, notes: Sequence[str]) -> tuple[Path, Path]:
        """The markdown to `md_path` and the CSV beside it (same name, .csv), each atomically."""
        csv_path = Path(md_path).with_suffix(".csv")
        write_atomic(Path(md_path), self.markdown(heading, notes).encode())
        write_atomic(csv_path, self.csv().encode())
        return Path(md_path), csv_path


def controller_table(sampler: Sampler, make: MakeController, objects: list[str], categories: dict[str, str],
                     first_seed: int, episodes_per_object: int, horizon: int, desc: str) -> ControllerTable:
    """`episodes_per_object` episodes per object of the controller `make` builds, on the
    sampler's workers (envs of `horizon` steps over `objects`); raises if a worker died."""
    jobs = [(name, first_seed + i) for name in objects for i in range(episodes_per_object)]
    start = time.perf_counter()
    results = sampler.map(partial(controller_episode, make), None, jobs, desc)
    if len(results) != len(jobs):
        raise DexdrakeError(f"{len(jobs) - len(results)} episodes were lost with their workers; run again")
    table = ControllerTable(list(objects), first_seed, episodes_per_object, horizon, categories,
                            wall_s=time.perf_counter() - start)
    for (name, _), episode in zip(jobs, results, strict=True):
        table.episodes.setdefault(name, []).append(episode)
    return table


# ------------------------------------------------------------------- the expert's variants
def hand_variants(hand: HandDescription) -> list[str]:
    """The variants `hand` can take: those whose named grasp poses its description has."""
    return [name for name, v in VARIANTS.items()
            if all(v.get(key, "") in ("", *hand.grasp_poses) for key in ("closed_pose", "open_pose"))]


def best_variant(variants: list[str], seeds: list[int], succeeds: Callable[[str, int], bool],
                 handicaps: dict[str, int] = HANDICAPS) -> tuple[str, dict[str, list[bool]]]:
    """The variant with the highest score over `seeds`, its successes less its handicap
    (ties: the earlier one), and each variant's outcomes on the seeds it tried: a variant
    stops once even success on all its remaining seeds could not beat the best score so
    far, so it could not have been chosen."""
    best, best_score, tried = variants[0], float("-inf"), {}
    for variant in variants:
        outcomes: list[bool] = []
        handicap = handicaps.get(variant, 0)
        for seed in seeds:
            if sum(outcomes) + len(seeds) - len(outcomes) - handicap <= best_score:
                break
            outcomes.append(succeeds(variant, seed))
        tried[variant] = outcomes
        if len(outcomes) == len(seeds) and sum(outcomes) - handicap > best_score:
            best, best_score = variant, sum(outcomes) - handicap
    return best, tried


MakeVariant = Callable[[dict[str, Any], Any], MakeController]
"""(GraspScript overrides, env) -> the expert with the hand's grasp script so changed; picklable."""


def variant_trials(make_variant: MakeVariant, env: Any, policy: None,
                   job: tuple[str, tuple[str, ...], tuple[int, ...]]) -> tuple[str, str, dict[str, list[bool]]]:
    """The trials of one object (job = (object, variants, seeds)): (object, chosen variant,
    each variant's outcomes); a sampler Episode with `make_variant` bound first."""
    name, variants, seeds = job

    def succeeds(variant: str, seed: int) -> bool:
        return env.rollout(partial(make_variant, VARIANTS[variant]), seed, object_name=name).success

    return name, *best_variant(list(variants), list(seeds), succeeds)


def choose_variants(sampler: Sampler, make_variant: MakeVariant, hand: HandDescription, objects: list[str],
                    seeds: list[int], horizon: int, command: str, old: dict[str, Any] | None = None) -> dict[str, Any]:
    """The expert's grasp table for `hand`: each of `objects` tried with every variant the
    hand can take on `seeds` (envs of `horizon` steps), the best chosen. With `old` (the
    existing table) only `objects` are re-chosen, each noting `command` and `seeds` (the table's
    own seeds are its first choice's); the other entries are kept, the variants added since
    shown as untried."""
    variants = {v: VARIANTS[v] for v in hand_variants(hand)}
    jobs = [(name, tuple(variants), tuple(seeds)) for name in objects]
    results = sampler.map(partial(variant_trials, make_variant), None, jobs, "objects")
    if len(results) != len(jobs):
        raise DexdrakeError(f"{len(jobs) - len(results)} objects were lost with their workers; run again")
    chosen = {name: {"variant": best, "successes": {v: sum(ok) for v, ok in tried.items()},
                     "tries": {v: len(ok) for v, ok in tried.items()}} for name, best, tried in results}
    if old is not None:
        for entry in chosen.values():
            entry["command"], entry["seeds"] = command, seeds
        chosen = {**old["objects"], **chosen}
        for entry in chosen.values():  # kept objects: the variants added since are untried
            for v in variants:
                entry["successes"].setdefault(v, 0)
                entry["tries"].setdefault(v, 0)
    return {"hand": hand.name, "command": old["command"] if old else command,
            "seeds": old["seeds"] if old else seeds, "horizon": horizon,
            "variants": variants, "objects": chosen}


def choice_lines(table: dict[str, Any]) -> list[str]:
    """One line per object (its variant and every variant's successes/tries), then the totals."""
    objects = table["objects"]
    lines = [f"{name:18s} {o['variant']:10s} " + " ".join(f"{v}={o['successes'][v]}/{o['tries'][v]}"
                                                          for v in o["successes"])
             for name, o in objects.items()]
    chosen = sum(o["successes"][o["variant"]] for o in objects.values())
    tries = sum(sum(o["tries"].values()) for o in objects.values())
    total = sum(len(o.get("seeds", table["seeds"])) for o in objects.values())
    lines.append(f"chosen per object: {chosen}/{total}; {tries} of {total * len(table['variants'])} trials run "
                 "(the rest could not change a choice)")
    return lines

