"""What every pipeline's stages share: :class:`Pipeline` (run stages in order, time each),
:class:`ConfiguredStage` (a stage holding the config sections it reads, and no others) and the
``Progress`` callback type. Below every pipeline (N-view, two-view, calibration)."""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Callable
from typing import Any, ClassVar

from torch import nn

from torchsfm.config import Config
from torchsfm.errors import ConfigError

Progress = Callable[[str], None]


class Pipeline(nn.Sequential):
    """Stages run in order on a state object (the N-view :class:`~torchsfm.sfm.stages.ViewSet`,
    the two-view :class:`~torchsfm.sfm.two_view.PairState`, the calibration's
    :class:`~torchsfm.calibration.stages.BoardViews`); each stage's seconds go to
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
    """A stage holding the config sections it reads — ``SECTIONS``, names of
    :class:`~torchsfm.config.Config` fields — and no others.

    Build it from those sections (``VerifyPairs(fundamental=FundamentalConfig(...))``; a section
    not given keeps its defaults) or pick them from a whole config
    (``VerifyPairs.from_config(config)``). ``self.config`` is a ``Config`` made of those sections
    only, for the library functions the stage calls: reading any other section of it raises a
    :class:`~torchsfm.errors.ConfigError`, so a stage cannot depend on a setting it does not
    declare."""

    SECTIONS: ClassVar[tuple[str, ...]] = ()

    def __init__(self, **sections: Any) -> None:
        super().__init__()
        name = type(self).__name__
        unknown = sorted(set(sections) - set(self.SECTIONS))
        if unknown:
            raise ConfigError(f"{name} reads the config sections {', '.join(self.SECTIONS)}; it takes no {', '.join(unknown)}")
        defaults = Config()
        self.config = Config(**{field.name: sections.get(field.name, getattr(defaults, field.name)) if field.name in self.SECTIONS
                                else UndeclaredSection(name, field.name) for field in dataclasses.fields(Config)})

    @classmethod
    def from_config(cls, config: Config, **arguments: Any) -> ConfiguredStage:
        """The stage with its ``SECTIONS`` taken from ``config`` (and any other constructor
        ``arguments``)."""
        return cls(**{name: getattr(config, name) for name in cls.SECTIONS}, **arguments)

    def extra_repr(self) -> str:
        return f"sections: {', '.join(self.SECTIONS)}"


class UndeclaredSection:
    """What a stage's config holds in place of a section the stage does not declare: reading any
    of its settings raises a ConfigError that names the stage and the section."""

    def __init__(self, stage: str, section: str) -> None:
        self.stage, self.section = stage, section

    def __getattr__(self, name: str) -> Any:
        if name.startswith("__") or name in ("stage", "section"):  # protocols (copy, pickle) look these up
            raise AttributeError(name)
        raise ConfigError(f"{self.stage} reads config {self.section}.{name}, but {self.section!r} is not among its SECTIONS")

    def __repr__(self) -> str:
        return f"<{self.section}: not a section of {self.stage}>"
