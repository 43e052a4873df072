"""How much the objects weigh in a hand's scenes (its description's `object_mass`).

DexRepNet's experiments give every object 0.5 kg (PAPER_MASS; specs/dexrepnet.md), the
default. A hand deployed on real objects (the Allegro on the Z1) weighs them instead as
household objects: the solid mesh's volume times a density, kept within [min_kg, max_kg]
(the solid meshes of hollow objects, a mug or a box, overstate their volume)."""

from __future__ import annotations

from dataclasses import dataclass

from dexdrake.errors import DexdrakeError

PAPER_MASS = 0.5  # kg: every object of the paper's experiments


@dataclass(frozen=True)
class ObjectMass:
    """`density` (kg/m^3) times the mesh volume, within [min_kg, max_kg]; density None: PAPER_MASS."""

    density: float | None = None
    min_kg: float = 0.05
    max_kg: float = PAPER_MASS

    def __post_init__(self) -> None:
        if self.density is not None and not self.density > 0:
            raise DexdrakeError(f"object_mass: density must be positive (kg/m^3), got {self.density}")
        if not 0 < self.min_kg <= self.max_kg:
            raise DexdrakeError(f"object_mass: needs 0 < min_kg <= max_kg, got {self.min_kg} and {self.max_kg}")

    def describe(self) -> str:
        """In words, for tables: "the paper's 0.5 kg" or the density and bounds."""
        if self.density is None:
            return f"the paper's {PAPER_MASS:g} kg"
        return f"mesh volume x {self.density:g} kg/m^3, {self.min_kg:g} to {self.max_kg:g} kg"

    def of(self, volume: float) -> float:
        """The mass (kg) of an object whose mesh encloses `volume` (m^3)."""
        if self.density is None:
            return PAPER_MASS
        return min(max(self.density * volume, self.min_kg), self.max_kg)
