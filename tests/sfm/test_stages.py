"""The pipelines as stages: run a prefix, swap a stage for a user-written one, insert one."""

from __future__ import annotations

import dataclasses
from dataclasses import replace
from types import SimpleNamespace

import pytest
import torch
from torch import nn

import torchsfm
from torchsfm.actions import SAMPLE
from torchsfm.config import MatchingConfig
from torchsfm.errors import ConfigError
from torchsfm.images import read_image
from torchsfm.sfm.from_tracks import ReconstructObjects
from torchsfm.pipeline import ConfiguredStage
from torchsfm.sfm.stages import MatchPairs, ViewSet, _better_of, default_pipeline, joining_pairs
from torchsfm.sfm.two_view import PairState, TwoViewReconstruction
from torchsfm.sfm.view_pairs import PairMatches, putative_matches

K = torch.tensor([[689.87, 0.0, 380.0], [0.0, 691.04, 251.0], [0.0, 0.0, 1.0]], dtype=torch.float64)


def _images():
    return [read_image(SAMPLE / f"000{v}.jpg") for v in (4, 5, 6)]


def test_a_prefix_gives_verified_pairs_only():
    pipeline = default_pipeline()
    state = pipeline[:3](ViewSet.of(_images(), K))
    assert state.pairs and state.tracks is None and state.reconstruction is None
    assert all(int(m.index1.numel()) >= 30 for m in state.pairs.values())
    assert set(state.timings) == {"DetectCorners", "MatchPairs", "VerifyPairs"}


class OnlyConsecutivePairs(nn.Module):
    """A user's stage in place of MatchPairs: the default matcher, then only pairs (i, i+1)."""

    def __init__(self) -> None:
        super().__init__()
        self.config = torchsfm.Config()
        self.calls = 0

    def forward(self, state: ViewSet) -> ViewSet:
        self.calls += 1
        matches, _ = putative_matches(state.greys, state.raw, self.config, state.generator, state.report)
        state.putative = {pair: m for pair, m in matches.items() if pair[1] == pair[0] + 1}
        return state


def test_swapping_a_stage():
    pipeline = default_pipeline()
    assert isinstance(pipeline[1], MatchPairs)
    mine = OnlyConsecutivePairs()
    pipeline[1] = mine
    model = torchsfm.reconstruct(_images(), K, pipeline=pipeline)
    assert mine.calls == 1 and model.num_views == 3 and model.num_points > 300
    assert "OnlyConsecutivePairs" in model.timings


class LeftHalfOnly(nn.Module):
    """A user's stage for the two-view pipeline: keep the matches in image1's left half."""

    def forward(self, state: PairState) -> PairState:
        state.static &= state.x1[:, 0] < state.images[0].shape[-1] / 2
        return state


def test_two_view_stages_insert_a_user_stage():
    images = _images()
    pipeline = TwoViewReconstruction()
    assert [type(stage).__name__ for stage in pipeline.stages] == [
        "DetectPairCorners", "MatchPair", "RejectMovingMatches", "EstimatePose", "BuildPairModel"]
    pipeline.stages.insert(2, LeftHalfOnly())
    model = pipeline(images[0], images[1], K, generator=torch.Generator().manual_seed(0))
    first_view = model.keypoints[model.observation_views == 0]
    assert model.num_points > 50 and bool((first_view[:, 0] < images[0].shape[-1] / 2).all())
    assert "LeftHalfOnly" in model.timings


def test_a_stage_holds_only_its_config_sections():
    config = torchsfm.Config()
    config = replace(config, matching=replace(config.matching, ncc_threshold=0.7), harris=replace(config.harris, max_corners=99))
    stage = MatchPairs.from_config(config)
    assert stage.config.matching.ncc_threshold == 0.7 and stage.config.pairs == config.pairs
    with pytest.raises(ConfigError, match="MatchPairs reads config harris.max_corners"):
        stage.config.harris.max_corners
    built = MatchPairs(matching=MatchingConfig(ncc_threshold=0.7))  # the sections not given keep their defaults
    assert built.config.matching == stage.config.matching and built.config.reconstruction == torchsfm.Config().reconstruction
    with pytest.raises(ConfigError, match="takes no harris"):
        MatchPairs(harris=config.harris)


def test_every_default_stage_declares_what_it_reads():
    """The whole default pipeline, the rematching, the moving-object decision and the per-body
    models run on stages holding only their sections: an undeclared read would raise."""
    config = torchsfm.Config()
    config = replace(config, moving_objects=replace(config.moving_objects, enabled=True, reconstruct_objects=True))
    pipeline = default_pipeline(config)
    pipeline.append(ReconstructObjects.from_config(config))
    assert all(set(stage.SECTIONS) < {field.name for field in dataclasses.fields(config)}
               for stage in pipeline if isinstance(stage, ConfiguredStage))
    model = torchsfm.reconstruct(_images(), K, pipeline=pipeline)
    assert model.num_views == 3 and model.segmented_tracks is not None


def test_only_the_strongest_bridge_joins_two_groups():
    """Views 0-2 form the model, 3-4 a separate one, 5 stands alone: of the bridges 2-3 (40
    matches), 0-4 (90) and 1-5 (30), 4-5 (50), only 0-4 joins the two models (the stronger of
    the two that do) and 4-5 brings view 5 (1-5, weaker, would join what is already joined)."""
    def bridge(count: int) -> PairMatches:
        return PairMatches(torch.arange(count), torch.arange(count), 0.5, torch.eye(3))

    bridges = {(2, 3): bridge(40), (0, 4): bridge(90), (1, 5): bridge(30), (4, 5): bridge(50), (0, 1): bridge(99)}
    assert sorted(joining_pairs(bridges, [[0, 1, 2], [3, 4]], 6)) == [(0, 4), (4, 5)]


def test_of_two_models_the_one_with_more_views_then_fewer_loose_then_more_points_is_kept():
    """A retry is kept when its model registers more views; with as many, when fewer of them
    were resected loosely; with as many of both, when it holds more points (a model a wrong pair
    started holds few: a second view seldom confirms chance matches). A full tie keeps the first."""
    def state(views: int, loose: int, points: int):
        model = SimpleNamespace(view_indices=list(range(views)), loose_resections=dict.fromkeys(range(loose), 8.0), num_points=points)
        return SimpleNamespace(reconstruction=model, report=lambda message: None)

    first = state(2, 0, 29)
    assert _better_of(first, more := state(3, 1, 10)) is more
    assert _better_of(state(3, 1, 500), tighter := state(3, 0, 10)) is tighter
    assert _better_of(first, denser := state(2, 0, 233)) is denser
    assert _better_of(first, state(2, 0, 29)) is first
    assert _better_of(denser, first) is denser
