"""without_autograd: the entry points run in inference mode and hand back ordinary tensors."""

from __future__ import annotations

from collections import namedtuple
from dataclasses import dataclass

import pytest
import torch

import torchsfm
from torchsfm.inference import ordinary_tensors
from torchsfm.testing import synthetic_two_view

ENTRY_POINTS = ["estimate_fundamental", "estimate_relative_pose", "estimate_absolute_pose", "reconstruct", "reconstruct_tracks",
                "reconstruct_motions", "bundle_adjust", "reject_moving_objects", "reject_moving_objects_in_tracks", "segment_motions",
                "detect_chessboard", "calibrate_camera"]

Pair = namedtuple("Pair", "first second")


@dataclass
class Holder:
    tensor: torch.Tensor
    nested: dict
    label: str


@pytest.mark.parametrize("name", ENTRY_POINTS)
def test_every_public_estimator_runs_without_autograd(name):
    assert getattr(getattr(torchsfm, name), "__wrapped__", None) is not None, f"{name} is not decorated with without_autograd"


def test_results_are_ordinary_tensors_with_the_values_of_a_plain_run():
    scene = synthetic_two_view(300, noise=0.5, outlier_ratio=0.3, seed=3)
    result = torchsfm.estimate_fundamental(scene.x1, scene.x2, generator=torch.Generator().manual_seed(0))
    plain = torchsfm.estimate_fundamental.__wrapped__(scene.x1, scene.x2, generator=torch.Generator().manual_seed(0))
    for name, value in vars(result).items():
        assert not value.is_inference(), name
        torch.testing.assert_close(value, getattr(plain, name), rtol=0, atol=0)
    result.inlier_mask[0] = ~result.inlier_mask[0]  # in place, outside inference mode: allowed on ordinary tensors
    F = result.F.clone().requires_grad_()
    (F * result.F).sum().backward()  # and usable by autograd
    torch.testing.assert_close(F.grad, result.F, rtol=0, atol=0)


def test_inside_the_callers_inference_mode_nothing_is_copied():
    scene = synthetic_two_view(100, noise=0.5, seed=1)
    with torch.inference_mode():
        result = torchsfm.estimate_fundamental(scene.x1, scene.x2)
    assert result.F.is_inference() and result.inlier_mask.is_inference()


def test_nested_containers_are_converted_and_ordinary_tensors_kept_as_they_are():
    ordinary = torch.arange(3.0)
    with torch.inference_mode():
        made = [torch.ones(2) * k for k in range(4)]
    holder = Holder(made[0], {(0, 1): Pair(made[1], [made[2], (made[3], ordinary)])}, "name")
    converted = ordinary_tensors(holder)
    pair = converted.nested[(0, 1)]
    tensors = [converted.tensor, pair.first, pair.second[0], pair.second[1][0]]
    assert isinstance(pair, Pair) and converted.label == "name"
    assert all(not t.is_inference() for t in tensors)
    torch.testing.assert_close(torch.stack(tensors), torch.stack(made), rtol=0, atol=0)
    assert pair.second[1][1] is ordinary
