"""Episode-seed ranges: training, validation and test seeds never meet.

An episode seed fixes the object placement (and, in training, the action noise). Every
seed a training run draws lies in TRAINING_SEEDS (DAPG by construction, DAgger and the
demo recorders by a check at their start: `check_training_seeds`). Evaluations
(`dexdrake eval`) draw from EVALUATION_SEEDS, above every training seed, in three parts:

- VALIDATION_SEEDS [1.5e9, 2e9): every choice (iterate, variant, setting) is measured here;
- TEST_SEEDS [2e9, 2.1e9): measured once per shipped policy, for its published tables only;
- the rest, [1e9, 1.5e9), "custom": evaluable (to reproduce tables measured there) but
  neither validation nor test.

A block of seeds S..S+N-1 lies in one part or is refused. All ranges end below 2**31.
"""

from __future__ import annotations

from collections.abc import Iterable

from dexdrake.errors import DexdrakeError

TRAINING_SEEDS = range(0, 10**9)
EVALUATION_SEEDS = range(10**9, 2_100_000_000)
VALIDATION_SEEDS = range(1_500_000_000, 2_000_000_000)
TEST_SEEDS = range(2_000_000_000, 2_100_000_000)
CUSTOM_SEEDS = range(EVALUATION_SEEDS.start, VALIDATION_SEEDS.start)
SEED_RANGES = {"validation": VALIDATION_SEEDS, "test": TEST_SEEDS, "custom": CUSTOM_SEEDS}
FIRST_VALIDATION_SEED = VALIDATION_SEEDS.start
FIRST_TEST_SEED = TEST_SEEDS.start


def describe(r: range) -> str:
    return f"[{r.start}, {r.stop})"


def check_training_seeds(seeds: Iterable[int], what: str = "training seeds") -> None:
    """Raise unless every seed lies in TRAINING_SEEDS (below validation and test)."""
    bad = [s for s in seeds if s not in TRAINING_SEEDS]
    if bad:
        raise DexdrakeError(f"{what} must lie in {describe(TRAINING_SEEDS)}, below the validation "
                            f"{describe(VALIDATION_SEEDS)} and test {describe(TEST_SEEDS)} seeds; got {bad[:3]}")


def seed_range(first: int, count: int) -> str | None:
    """'validation', 'test' or 'custom': the part of EVALUATION_SEEDS holding all of seeds
    first .. first+count-1; None when they leave it or straddle two parts."""
    last = first + count - 1
    return next((name for name, r in SEED_RANGES.items() if count >= 1 and first in r and last in r), None)


def check_evaluation_seeds(first: int, count: int) -> str:
    """The seed range ('validation' | 'test' | 'custom') of seeds first .. first+count-1; raise
    unless they lie in one."""
    name = seed_range(first, count)
    if name is None:
        parts = ", ".join(f"{n} {describe(r)}" for n, r in SEED_RANGES.items())
        raise DexdrakeError(f"evaluation seeds {first}..{first + count - 1} must lie in one of {parts} (all above "
                            f"every training seed); validation starts at {FIRST_VALIDATION_SEED}, test at "
                            f"{FIRST_TEST_SEED}")
    return name
