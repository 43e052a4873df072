"""Drake LeafSystems and diagram builders (installed as dexdrake.systems)."""
