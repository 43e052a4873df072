"""Episode-seed ranges: evaluation seeds are reserved, disjoint from every training seed.

An episode seed fixes the object placement (and, in training, the action noise). Training
(DAPG rollouts) draws its seeds in TRAINING_SEEDS by construction; the evaluation protocol
(`dexdrake eval`) draws its seeds in EVALUATION_SEEDS, so no evaluation episode replays a
training episode. DAgger's seeds (seed * 10**6 + iteration * 10**4 + k) stay in
TRAINING_SEEDS for run seeds below 1000. Choices (iterate, variant) are measured on the
validation block from FIRST_VALIDATION_SEED; a shipped result once, on the test block from
FIRST_TEST_SEED (`dexdrake train recipe`).
"""

from __future__ import annotations

from collections.abc import Iterable

from dexdrake.errors import DexdrakeError

TRAINING_SEEDS = range(0, 10**9)
EVALUATION_SEEDS = range(10**9, 2_100_000_000)
FIRST_EVALUATION_SEED = EVALUATION_SEEDS.start
FIRST_VALIDATION_SEED = 1_500_000_000
FIRST_TEST_SEED = 2_000_000_000


def _describe(r: range) -> str:
    return f"[{r.start}, {r.stop})"


def check_training_seeds(seeds: Iterable[int]) -> None:
    """Raise unless every seed lies in TRAINING_SEEDS."""
    bad = [s for s in seeds if s not in TRAINING_SEEDS]
    if bad:
        raise DexdrakeError(f"training seeds must lie in {_describe(TRAINING_SEEDS)} (evaluation owns "
                            f"{_describe(EVALUATION_SEEDS)}); got {bad[:3]}")


def evaluation_seeds_reserved(first: int, count: int) -> bool:
    """True when seeds first .. first+count-1 all lie in EVALUATION_SEEDS."""
    return count >= 1 and first in EVALUATION_SEEDS and first + count - 1 in EVALUATION_SEEDS


def check_evaluation_seeds(first: int, count: int) -> None:
    """Raise unless seeds first .. first+count-1 all lie in EVALUATION_SEEDS."""
    if not evaluation_seeds_reserved(first, count):
        raise DexdrakeError(f"evaluation seeds {first}..{first + count - 1} leave the range reserved for evaluation "
                            f"{_describe(EVALUATION_SEEDS)} (disjoint from every training seed); "
                            f"start at {FIRST_EVALUATION_SEED}")
