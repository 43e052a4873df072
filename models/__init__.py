"""Robot models, object sets and trained weights shipped with dexdrake."""
