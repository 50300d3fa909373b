"""The two-view pipeline on real images with ground truth (issue #3's bar).

Strecha fountain-P11 and Herz-Jesu-P8 (768×512), every neighbouring pair, and Oxford Merton
College I (1024×768), every pair: ≥ 300 final matches, ≥ 95% of them within 1.5 px (symmetric
epipolar distance) of the ground-truth epipolar geometry, rotation error < 0.5°, translation
direction error < 2°.
"""

import pytest
import torch

from torchsfm.geometry.fundamental import fundamental_from_pose, fundamental_from_projections, symmetric_epipolar_distance
from torchsfm.io.datasets import read_oxford_multiview, read_strecha
from torchsfm.io.images import read_image
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


@pytest.mark.parametrize("name", ["strecha_fountain_P11", "strecha_herzjesu_P8"])
def test_strecha_neighbouring_pairs(shared_data, name):
    sequence = read_strecha(shared_data / name)
    for i in range(len(sequence.images) - 1):
        j = i + 1
        model = PIPELINE(read_image(sequence.images[i]), read_image(sequence.images[j]), sequence.K[i], sequence.K[j],
                         generator=torch.Generator().manual_seed(0))
        R_true, t_true = sequence.relative_pose(i, j)
        _check(model, fundamental_from_pose(sequence.K[i], sequence.K[j], R_true, t_true), R_true, t_true, f"{name} {i}-{j}")


def test_merton_pairs(shared_data):
    dataset = read_oxford_multiview(shared_data / "oxford_merton1")
    K, _, _ = dataset.cameras()
    for i, j in ((0, 1), (1, 2), (0, 2)):
        model = PIPELINE(read_image(dataset.images[i]), read_image(dataset.images[j]), K[i], K[j],
                         generator=torch.Generator().manual_seed(0))
        R_true, t_true = dataset.relative_pose(i, j)
        _check(model, fundamental_from_projections(dataset.P[i], dataset.P[j]), R_true, t_true, f"merton {i}-{j}")
