"""Parameterised gmsh geometries with named physical groups (pure functions on a gmsh model)."""
