"""Data package: the URDFs, meshes and scene files shipped with multibody-sim (no code)."""
