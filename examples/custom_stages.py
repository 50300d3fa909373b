"""The N-view pipeline as stages: run a prefix, configure one stage, swap in a user-written one.

On the bundled three fountain views (``torchsfm/data/fountain``, K and ground-truth poses
included):

1. the first three stages only (corners, matches, verified pairs);
2. the default pipeline, then the same with ``VerifyPairs`` built from its own config section
   (the 7-point solver inside RANSAC): each stage holds the sections it reads and no others;
3. a user-written stage in place of ``MatchPairs``: the default matcher, then only the pairs of
   consecutive views;

printing for each the views registered, the points and the camera errors against the ground
truth, and the seconds per stage.

    python examples/custom_stages.py
"""

from __future__ import annotations

import torch
from torch import nn

import torchsfm
from torchsfm.actions import SAMPLE
from torchsfm.config import FundamentalConfig
from torchsfm.evaluation import camera_errors
from torchsfm.images import read_image
from torchsfm.io.datasets import read_strecha
from torchsfm.sfm.stages import MatchPairs, VerifyPairs, ViewSet, default_pipeline


class ConsecutivePairsOnly(nn.Module):
    """A user's stage in place of MatchPairs: the default matcher, then only pairs (i, i + 1)."""

    def __init__(self) -> None:
        super().__init__()
        self.matcher = MatchPairs()

    def forward(self, state: ViewSet) -> ViewSet:
        state = self.matcher(state)
        state.putative = {pair: matches for pair, matches in state.putative.items() if pair[1] == pair[0] + 1}
        return state


def summary(model: torchsfm.Reconstruction, sample) -> str:
    errors = camera_errors(model.cameras.R, model.cameras.t, sample.R[model.view_indices], sample.t[model.view_indices])
    stages = ", ".join(f"{name} {seconds:.2f}" for name, seconds in model.timings.items())
    return (f"{model.num_views} views, {model.num_points} points, centre error {100 * float(errors.centre.max()) / errors.extent:.3f}% "
            f"of the path, rotation error {float(errors.rotation.max()):.3f} deg\n    seconds: {stages}")


def main() -> None:
    sample = read_strecha(SAMPLE)
    images = [str(path) for path in sample.images]
    seeded = lambda: torch.Generator().manual_seed(0)  # noqa: E731

    pipeline = default_pipeline()
    state = pipeline[:3](ViewSet.of([read_image(path) for path in images], sample.K[0], generator=seeded()))
    print("prefix DetectCorners, MatchPairs, VerifyPairs: verified pairs "
          + ", ".join(f"{i}-{j} ({m.index1.numel()} matches)" for (i, j), m in state.pairs.items()))

    print("default pipeline:", summary(torchsfm.reconstruct(images, sample.K[0], generator=seeded()), sample))

    pipeline = default_pipeline()
    pipeline[2] = VerifyPairs(fundamental=FundamentalConfig(minimal_solver="seven_point"))
    print(f"with {pipeline[2]}:", summary(torchsfm.reconstruct(images, sample.K[0], pipeline=pipeline, generator=seeded()), sample))

    pipeline = default_pipeline()
    pipeline[1] = ConsecutivePairsOnly()
    print("with a user's ConsecutivePairsOnly:", summary(torchsfm.reconstruct(images, sample.K[0], pipeline=pipeline,
                                                                                generator=seeded()), sample))


if __name__ == "__main__":
    main()
