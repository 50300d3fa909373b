"""Camera files (--K text with distortion, calib.yaml) and ``torchsfm calibrate``."""

import pytest
import torch
import yaml
from torch.testing import assert_close

from torchsfm.calibration.files import read_camera
from torchsfm.cli import main
from torchsfm.errors import InputError, ShapeError
from torchsfm.testing import render_chessboard, visible_board_poses, wide_angle_camera
from torchsfm.visualization import write_png

K_TRUE, DISTORTION_TRUE = wide_angle_camera()


def test_text_camera_with_and_without_distortion(tmp_path):
    plain = tmp_path / "K.txt"
    plain.write_text("500 0 330\n0 495 235\n0 0 1  # K\n")
    K, distortion = read_camera(plain)
    assert_close(K, K_TRUE)
    assert_close(distortion, torch.zeros(2, dtype=torch.float64))
    with_distortion = tmp_path / "camera.txt"
    with_distortion.write_text("500 0 330\n0 495 235\n0 0 1\n-0.25 0.08\n")
    assert_close(read_camera(with_distortion)[1], DISTORTION_TRUE)


@pytest.mark.parametrize("content, error, message", [
    ("500 0 330\n0 495 235\n0 0 1\n-0.25\n", ShapeError, "k1 k2"),
    ("500 0 330\n0 495 235\n", ShapeError, "3x3"),
    ("500 0 330\n0 495 235\n0 0 1\nnan 0\n", InputError, "finite"),
])
def test_bad_camera_files(tmp_path, content, error, message):
    path = tmp_path / "camera.txt"
    path.write_text(content)
    with pytest.raises(error, match=message):
        read_camera(path)


def _board_photos(folder, count):
    R, t = visible_board_poses(count, 0, K_TRUE, DISTORTION_TRUE)
    paths = []
    for view in range(count):
        paths.append(folder / f"board{view}.png")
        write_png(paths[-1], render_chessboard(K_TRUE, DISTORTION_TRUE, R[view], t[view], (9, 7)).expand(3, -1, -1))
    return paths


def test_calibrate_command_writes_the_calibration_and_the_corner_pictures(tmp_path, capsys):
    photos = tmp_path / "photos"
    photos.mkdir()
    _board_photos(photos, 6)
    write_png(photos / "blank.png", torch.full((3, 480, 640), 128, dtype=torch.uint8))
    out = tmp_path / "calib.yaml"
    assert main(["calibrate", str(photos), "--pattern", "9x7", "--square", "25", "--out", str(out), "--quiet"]) == 0
    document = yaml.safe_load(out.read_text())
    assert len(document["views"]) == 6 and document["not_found"][0]["image"] == "blank.png"
    assert abs(document["K"][0][0] / 500 - 1) < 0.005 and document["rms_px"] < 0.2
    assert sorted(p.name for p in (tmp_path / "calib_corners").iterdir()) == [f"board{v}.png" for v in range(6)]
    printed = capsys.readouterr().out
    assert "no board in blank.png" in printed and "fx" in printed
    K, distortion = read_camera(out)  # what --K accepts
    assert_close(K, torch.tensor(document["K"], dtype=torch.float64))
    assert_close(distortion, torch.tensor(document["distortion"], dtype=torch.float64))


def _fails(arguments, capsys, message, out):
    assert main(arguments + ["--quiet"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("torchsfm: error: ") and message in err[0], err
    assert not out.exists()


def test_calibrate_errors(tmp_path, capsys):
    photos = tmp_path / "photos"
    photos.mkdir()
    paths = _board_photos(photos, 2)
    out = tmp_path / "calib.yaml"
    _fails(["calibrate", *map(str, paths), "--pattern", "9x7", "--out", str(out)], capsys, "found in 2 of 2 images, calibration needs 3", out)
    _fails(["calibrate", *map(str, paths), "--pattern", "8x6", "--out", str(out)], capsys, "larger than the 8x6 pattern", out)
    blank = tmp_path / "blank.png"
    write_png(blank, torch.full((3, 480, 640), 128, dtype=torch.uint8))
    _fails(["calibrate", str(blank), "--pattern", "9x7", "--out", str(out)], capsys, "found in 0 of 1 images", out)
