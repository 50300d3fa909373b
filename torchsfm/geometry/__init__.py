"""Multiple-view geometry: normalization, F, E, rotations, triangulation, refinements."""
