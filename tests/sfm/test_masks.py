"""Masks (COLMAP's convention: no features where a mask is black): a video's fixed overlay."""

from __future__ import annotations

import pytest
import torch

import torchsfm
from torchsfm.actions import SAMPLE, mask_paths
from torchsfm.cli import build_parser
from torchsfm.config import PairsConfig
from torchsfm.errors import InputError, ShapeError
from torchsfm.images import inside_mask, read_image, read_mask, reduce_mask
from torchsfm.sfm.incremental import per_image_masks
from torchsfm.sfm.pairs import coarse_features
from torchsfm.sfm.sift import sift_features
from torchsfm.sfm.stages import ViewSet, default_pipeline
from torchsfm.visualization import write_png

K = torch.tensor([[689.87, 0.0, 380.0], [0.0, 691.04, 251.0], [0.0, 0.0, 1.0]], dtype=torch.float64)
STAMP = (slice(440, 488), slice(40, 232))  # rows, columns of the overlay in the 768x512 views


def _stamped_views() -> tuple[list[torch.Tensor], torch.Tensor]:
    """Fountain-P11 views 4-6 (bundled) with one high-contrast block pattern at the same pixels of
    every view (a time stamp burnt into a video), and the mask that leaves it out."""
    blocks = torch.rand(6, 24, generator=torch.Generator().manual_seed(0)) > 0.5
    pattern = (blocks.repeat_interleave(8, 0).repeat_interleave(8, 1) * 255).to(torch.uint8)
    views = []
    for v in (4, 5, 6):
        image = read_image(SAMPLE / f"000{v}.jpg").clone()
        image[(slice(None), *STAMP)] = pattern
        views.append(image)
    mask = torch.ones(512, 768, dtype=torch.bool)
    mask[STAMP] = False
    return views, mask


def _on_stamp(points: torch.Tensor) -> torch.Tensor:
    rows, columns = STAMP
    x, y = points[:, 0], points[:, 1]
    return (x > columns.start - 1) & (x < columns.stop) & (y > rows.start - 1) & (y < rows.stop)


def test_no_corner_coarse_corner_or_sift_keypoint_where_the_mask_is_black():
    views, mask = _stamped_views()
    unmasked = default_pipeline()[:1](ViewSet.of(views, K))
    assert all(int(_on_stamp(raw).sum()) > 20 for raw in unmasked.raw)  # the overlay is full of corners
    masked = default_pipeline()[:1](ViewSet.of(views, K, masks=[mask] * 3))
    assert all(not bool(_on_stamp(raw).any()) and raw.shape[0] > 1000 for raw in masked.raw)
    greys = masked.greys
    for masks, expected in ((None, True), ([mask] * 3, False)):
        coarse = coarse_features(greys, PairsConfig(), masks=masks)
        assert bool(_on_stamp(coarse.points[coarse.valid]).any()) == expected
    points, descriptors = sift_features(greys[:1], 2000, [mask])
    assert points[0].shape[0] == descriptors[0].shape[0] > 500 and not bool(_on_stamp(points[0]).any())


def test_a_reconstruction_with_a_mask_has_no_point_on_the_overlay():
    views, mask = _stamped_views()
    model = torchsfm.reconstruct(views, K, masks=mask, generator=torch.Generator().manual_seed(0))
    assert model.num_views == 3 and model.num_points > 500
    assert not bool(_on_stamp(model.keypoints).any())


def test_masks_that_do_not_fit_are_refused_naming_the_problem(tmp_path):
    views, mask = _stamped_views()
    with pytest.raises(InputError, match="2 masks for 3 images"):
        torchsfm.reconstruct(views, K, masks=[mask, mask])
    with pytest.raises(ShapeError, match="mask 1 is 384x256 px, its image 768x512 px"):
        torchsfm.reconstruct(views, K, masks=[None, mask[::2, ::2], None])
    with pytest.raises(InputError, match="cannot read image .*missing.png"):
        torchsfm.reconstruct(views, K, masks=tmp_path / "missing.png")


def test_one_mask_file_for_a_video_is_read_once_and_reduced_keeping_only_whole_blocks(tmp_path):
    views, mask = _stamped_views()
    path = tmp_path / "overlay.png"
    write_png(path, (mask * 255).to(torch.uint8).expand(3, -1, -1))
    assert torch.equal(read_mask(path), mask)
    mask_of = per_image_masks(path, 3)
    assert mask_of(0, views[0]) is mask_of(2, views[2])  # one tensor for the whole video
    half = reduce_mask(mask, 2)
    assert half.shape == (256, 384) and not bool(half[220:244, 20:116].any()) and bool(half[219, 20]) is True
    partly = mask.clone()
    partly[0, 1] = False  # one pixel of the first 2x2 block
    assert not bool(reduce_mask(partly, 2)[0, 0])
    assert inside_mask(torch.tensor([[100.0, 450.0], [100.0, 300.0]]), mask).tolist() == [False, True]


def test_masks_on_the_command_line_follow_colmaps_folder_convention(tmp_path):
    images = [tmp_path / "a.jpg", tmp_path / "b.jpg"]
    folder = tmp_path / "masks"
    folder.mkdir()
    (folder / "b.jpg.png").write_bytes(b"")
    assert mask_paths(folder, images) == [None, folder / "b.jpg.png"]
    assert mask_paths(folder / "b.jpg.png", images) == folder / "b.jpg.png"
    with pytest.raises(InputError, match="holds no mask named as COLMAP's"):
        mask_paths(tmp_path, images)
    with pytest.raises(InputError, match="neither a mask image nor a folder"):
        mask_paths(tmp_path / "nothing", images)
    args = build_parser().parse_args(["reconstruct", "a.jpg", "b.jpg", "--out", "o", "--masks", str(folder)])
    assert args.masks == folder
