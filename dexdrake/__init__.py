"""dexdrake: a Drake-based sim-to-real stack for DexRepNet dexterous grasping."""

__version__ = "0.1.0"
