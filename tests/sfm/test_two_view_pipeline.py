"""The two-view pipeline on real images with ground truth (issue #3's bar).

Strecha fountain-P11 and Herz-Jesu-P8 (768×512), every neighbouring pair, and Oxford Merton
College I (1024×768), every pair: ≥ 300 final matches, ≥ 95% of them within 1.5 px (symmetric
epipolar distance) of the ground-truth epipolar geometry, rotation error < 0.5°, translation
direction error < 2°.
"""

import torch

from torchsfm.geometry.fundamental import symmetric_epipolar_distance
from torchsfm.io.datasets import ground_truth_pairs
from torchsfm.images import read_image
from torchsfm.sfm.two_view import TwoViewReconstruction
from torchsfm.testing import rotation_error_deg, translation_direction_error_deg

PIPELINE = TwoViewReconstruction()


def _check(model, F_true, R_true, t_true, pair):
    inliers = model.inlier_mask
    distance = symmetric_epipolar_distance(F_true, model.matches[inliers, :2], model.matches[inliers, 2:])
    assert inliers.sum() >= 300, pair
    assert (distance < 1.5).double().mean() >= 0.95, pair
    assert rotation_error_deg(model.cameras.R[1], R_true) < 0.5, pair
    assert translation_direction_error_deg(model.cameras.t[1], t_true) < 2.0, pair
    assert model.num_points == int(inliers.sum()) and model.reprojection_rms() < 1.0


def test_every_ground_truth_pair(shared_data):
    for pair in ground_truth_pairs(shared_data):
        model = PIPELINE(read_image(pair.image1), read_image(pair.image2), pair.K1, pair.K2,
                         generator=torch.Generator().manual_seed(0))
        _check(model, pair.F, pair.R, pair.t, pair.name)
