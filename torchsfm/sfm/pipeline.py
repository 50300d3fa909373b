"""What every pipeline's stages share: :class:`Pipeline` (run stages in order, time each) and
:class:`ConfiguredStage` (a stage holding the config section it uses)."""

from __future__ import annotations

import time
from typing import Any

from torch import nn


class Pipeline(nn.Sequential):
    """Stages run in order on a state object (the N-view :class:`~torchsfm.sfm.stages.ViewSet`,
    the two-view :class:`~torchsfm.sfm.two_view.PairState`); each stage's seconds go to
    ``state.timings`` under its class name. ``nn.Sequential``-like: index it, slice it for a
    prefix, replace or insert a stage."""

    def forward(self, state: Any) -> Any:
        for stage in self:
            start = time.perf_counter()
            state = stage(state)
            name = type(stage).__name__
            state.timings[name] = state.timings.get(name, 0.0) + time.perf_counter() - start
        return state


class ConfiguredStage(nn.Module):
    """A stage holding the config (section) it uses; ``repr`` shows it."""

    def __init__(self, config: Any) -> None:
        super().__init__()
        self.config = config

    def extra_repr(self) -> str:
        return type(self.config).__name__
