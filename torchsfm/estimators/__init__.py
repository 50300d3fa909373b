"""Problem-level estimators on tensors: robust two-view geometry, calibrated relative pose,
absolute pose, and their LM refinements (above geometry, robust and optim; below moving and the
pipelines)."""
