"""The command line: the demo, the two-view command, and one clear line per bad input."""

import json
import subprocess
import sys

import kornia
import pytest
import torch

from torchsfm.actions import SAMPLE
from torchsfm.cli import main
from torchsfm.images import read_image
from torchsfm.visualization import write_png

IMAGE1, IMAGE2, K_FILE = SAMPLE / "0004.jpg", SAMPLE / "0005.jpg", SAMPLE / "K.txt"
OUTPUTS = {"model.wrl", "points.ply", "matches.png", "summary.json", "colmap"}


def test_demo_writes_every_output_and_recovers_the_ground_truth(tmp_path, capsys):
    assert main(["demo", "--out", str(tmp_path), "--quiet"]) == 0
    assert {p.name for p in tmp_path.iterdir()} == OUTPUTS
    assert {p.name for p in (tmp_path / "colmap").iterdir()} == {"cameras.txt", "images.txt", "points3D.txt"}
    summary = json.loads((tmp_path / "summary.json").read_text())
    assert summary["inliers"] >= 300 and summary["reprojection_rms_px"] < 0.5
    assert summary["ground_truth"]["rotation_error_deg"] < 0.5
    assert summary["ground_truth"]["translation_direction_error_deg"] < 2.0
    assert "against the ground truth" in capsys.readouterr().out


def test_two_view_with_overrides_and_progress(tmp_path, capsys):
    out = tmp_path / "model"
    code = main(["two-view", str(IMAGE1), str(IMAGE2), "--K", str(K_FILE), "--out", str(out),
                 "--set", "harris.max_corners=800", "--set", "matching.relaxation=winner_take_all"])
    assert code == 0
    summary = json.loads((out / "summary.json").read_text())
    assert summary["config"]["harris"]["max_corners"] == 800 and summary["inliers"] >= 100
    assert "matching ..." in capsys.readouterr().err


def _fails(tmp_path, capsys, arguments, message):
    out = tmp_path / "out"
    assert main(["two-view", *arguments, "--out", str(out), "--quiet"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("torchsfm: error: ") and message in err[0], err
    assert not out.exists()  # no output files on error


def test_missing_image(tmp_path, capsys):
    _fails(tmp_path, capsys, [str(tmp_path / "nope.jpg"), str(IMAGE2), "--K", str(K_FILE)], "no such file")
    _fails(tmp_path, capsys, [str(tmp_path), str(IMAGE2), "--K", str(K_FILE)], "a folder, not an image file")


def test_unreadable_image(tmp_path, capsys):
    bad = tmp_path / "bad.jpg"
    bad.write_bytes(b"not a jpeg")
    _fails(tmp_path, capsys, [str(bad), str(IMAGE2), "--K", str(K_FILE)], f"cannot read image {bad}")


def test_images_of_different_size(tmp_path, capsys):
    small = tmp_path / "small.png"
    write_png(small, read_image(IMAGE2)[:, :256, :384])
    _fails(tmp_path, capsys, [str(IMAGE1), str(small), "--K", str(K_FILE)], "differ in size: image1 is 768x512, image2 384x256")


def test_grey_and_colour_images_both_work(tmp_path):
    grey = tmp_path / "grey.png"
    colour = read_image(IMAGE2).float()
    write_png(grey, (0.299 * colour[0] + 0.587 * colour[1] + 0.114 * colour[2]).round().to(torch.uint8)[None].expand(3, -1, -1))
    assert main(["two-view", str(IMAGE1), str(grey), "--K", str(K_FILE), "--out", str(tmp_path / "m"), "--quiet"]) == 0


def test_sixteen_bit_images_are_read_with_their_contrast(tmp_path):
    """A 12-bit camera's 16-bit PNG (values up to 4080) reads back as the 8-bit image it was
    made from, and the two-view command runs on it."""
    image = read_image(IMAGE2)
    assert int(image.max()) == 255  # so the scaling is exact
    twelve_bit = tmp_path / "twelve_bit.png"
    kornia.io.write_image(twelve_bit, (image.to(torch.int32) * 16).to(torch.uint16).contiguous())
    assert torch.equal(read_image(twelve_bit), image)
    assert main(["two-view", str(IMAGE1), str(twelve_bit), "--K", str(K_FILE), "--out", str(tmp_path / "m"), "--quiet"]) == 0


@pytest.mark.parametrize("content, message", [
    ("1 0 0\n0 1 0\n", "3x3 matrix"),
    ("689 0 380\n0 0 251\n0 0 1\n", "K is singular"),
    ("a b c\n", "must hold numbers"),
])
def test_bad_intrinsics(tmp_path, capsys, content, message):
    K = tmp_path / "K.txt"
    K.write_text(content)
    _fails(tmp_path, capsys, [str(IMAGE1), str(IMAGE2), "--K", str(K)], message)


def test_textureless_image(tmp_path, capsys):
    flat = tmp_path / "flat.png"
    write_png(flat, torch.full((3, 512, 768), 128, dtype=torch.uint8))
    _fails(tmp_path, capsys, [str(flat), str(IMAGE2), "--K", str(K_FILE)], "flat.png has 0 corners")


def test_identical_images_have_no_baseline(tmp_path, capsys):
    _fails(tmp_path, capsys, [str(IMAGE1), str(IMAGE1), "--K", str(K_FILE)], "show no baseline")


def test_a_camera_turned_in_place_is_refused(tmp_path, capsys):
    """The first view warped by K R K⁻¹ (3° about y, 0.6° about x): every match is explained by
    the rotation, and the few mismatches F lets through along the epipolar lines fall on both
    sides of infinity, so no translation is determined — one clear error, no model."""
    from torchsfm.geometry.rotation import axis_angle_to_rotation
    from torchsfm.io.datasets import read_strecha

    K = read_strecha(SAMPLE).K[0].float()
    R = axis_angle_to_rotation(torch.tensor([0.01, 0.0524, 0.0], dtype=torch.float64)).float()
    image = read_image(IMAGE1).float()[None] / 255
    turned = kornia.geometry.transform.warp_perspective(image, (K @ R @ torch.linalg.inv(K))[None], image.shape[-2:])
    write_png(tmp_path / "turned.png", (turned[0] * 255).round().clamp(0, 255).to(torch.uint8))
    _fails(tmp_path, capsys, [str(IMAGE1), str(tmp_path / "turned.png"), "--K", str(K_FILE)],
           "show no parallax beyond noise")


def test_unknown_config_key(tmp_path, capsys):
    _fails(tmp_path, capsys, [str(IMAGE1), str(IMAGE2), "--K", str(K_FILE), "--set", "harris.kk=0.05"], "harris.kk")
    config = tmp_path / "c.yaml"
    config.write_text("matching:\n  radius: 3\n")
    _fails(tmp_path, capsys, [str(IMAGE1), str(IMAGE2), "--K", str(K_FILE), "--config", str(config)], "matching.radius")


@pytest.mark.parametrize("case, message", [("missing", "no such file or folder"), ("empty", "holds no images (.jpeg, .jpg, .png)"),
                                           ("out_is_a_file", "is a file")])
def test_reconstruct_refuses_a_wrong_path_before_any_work(tmp_path, capsys, case, message):
    (tmp_path / "empty").mkdir()
    (tmp_path / "file").write_text("x")
    inputs = {"missing": [str(tmp_path / "nope")], "empty": [str(tmp_path / "empty")]}.get(case, [str(IMAGE1), str(IMAGE2)])
    out = tmp_path / ("file" if case == "out_is_a_file" else "out")
    assert main(["reconstruct", *inputs, "--K", str(K_FILE), "--out", str(out), "--quiet"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("torchsfm: error: ") and message in err[0], err
    assert not (tmp_path / "out").exists() and (tmp_path / "file").read_text() == "x"


def test_a_refused_write_is_an_error_naming_the_file(tmp_path):
    from torchsfm.actions import write_files
    from torchsfm.errors import InputError

    (tmp_path / "taken").write_text("x")  # a file where the output folder should go
    with pytest.raises(InputError, match="cannot write .*taken/summary.json"):
        write_files(tmp_path / "taken", {"summary.json": "{}"})


def test_module_entry_point():
    result = subprocess.run([sys.executable, "-m", "torchsfm", "--help"], capture_output=True, text=True)
    assert result.returncode == 0 and "two-view" in result.stdout


def test_reconstruct_command_writes_the_model_and_a_summary(shared_data, tmp_path, capsys):
    folder = shared_data / "strecha_fountain_P11"
    images = [str(folder / f"000{v}.jpg") for v in range(4)]
    out = tmp_path / "sequence"
    assert main(["reconstruct", *images, "--K", str(K_FILE), "--sequential", "--out", str(out)]) == 0
    assert {p.name for p in out.iterdir()} == {"model.wrl", "points.ply", "colmap", "summary.json"}
    summary = json.loads((out / "summary.json").read_text())
    assert summary["views_registered"] == 4 and summary["points"] > 500
    assert summary["config"]["pairs"]["mode"] == "sequential" and summary["other_models"] == []
    assert set(summary["seconds"]) >= {"DetectCorners", "MatchPairs", "VerifyPairs", "MapIncrementally", "bundle adjustment", "total"}
    captured = capsys.readouterr()
    assert "registering view" in captured.err and "4 views registered" in captured.out


def test_reconstruct_reports_a_loose_or_tracked_resection(shared_data, tmp_path, capsys):
    """Fountain views 8, 0, 4 where a resection must keep 100 inliers: without tracking against
    the map view 0 registers at the widened 4 px threshold; with it (the default) it registers
    at 2 px from the model's points found where that pose puts them. Both the summary and the
    printout say which."""
    folder = shared_data / "strecha_fountain_P11"
    images = [str(folder / f"000{v}.jpg") for v in (8, 0, 4)]
    for tracking in ("false", "true"):
        out = tmp_path / tracking
        assert main(["reconstruct", *images, "--K", str(K_FILE), "--set", "reconstruction.min_resection_inliers=100", "--set",
                     f"reconstruction.track_against_map={tracking}", "--quiet", "--out", str(out)]) == 0
        summary = json.loads((out / "summary.json").read_text())
        printed = capsys.readouterr().out
        if tracking == "false":
            assert summary["loose_resections"] == [{"index": 0, "threshold_px": 4.0}] and summary["tracked_resections"] == []
            assert "view 0 registered at a widened resection threshold of 4 px" in printed
        else:
            assert summary["loose_resections"] == [] and [view["index"] for view in summary["tracked_resections"]] == [0]
            assert summary["tracked_resections"][0]["inliers"] >= 100 and summary["views_registered"] == 3
            assert "view 0 registered by tracking against the map" in printed


def test_reconstruct_reports_still_frames(shared_data, tmp_path, capsys):
    """A video that stops (fountain view 1 three times): frames 2 and 3 did not move from
    keyframe 1, and both the summary and the printout say they were resected, not adjusted."""
    folder = shared_data / "strecha_fountain_P11"
    images = [str(folder / f"000{v}.jpg") for v in (0, 1, 1, 1, 2)]
    out = tmp_path / "stops"
    assert main(["reconstruct", *images, "--K", str(K_FILE), "--quiet", "--out", str(out)]) == 0
    summary = json.loads((out / "summary.json").read_text())
    assert summary["views_registered"] == 5
    assert summary["still_frames"] == [{"index": 2, "keyframe": 1}, {"index": 3, "keyframe": 1}]
    assert "view 3: the camera did not move from view 1; resected from the model, not adjusted" in capsys.readouterr().out


def test_reconstruct_needs_two_images(tmp_path, capsys):
    assert main(["reconstruct", str(IMAGE1), "--K", str(K_FILE), "--out", str(tmp_path / "o"), "--quiet"]) == 2
    assert "at least 2 images, got 1" in capsys.readouterr().err
    assert not (tmp_path / "o").exists()


def test_reconstruct_without_K_reports_the_estimated_intrinsics(tmp_path, capsys):
    """The three bundled fountain views without --K: registered, and the estimated focal length
    written to the summary within 3% of the true 689.9 px (three views constrain it weakly)."""
    import json

    from torchsfm.actions import SAMPLE

    out = tmp_path / "model"
    code = main(["reconstruct", str(SAMPLE / "0004.jpg"), str(SAMPLE / "0005.jpg"), str(SAMPLE / "0006.jpg"),
                 "--out", str(out), "--quiet"])
    assert code == 0
    summary = json.loads((out / "summary.json").read_text())
    assert summary["views_registered"] == 3
    assert abs(summary["K"][0][0] / 689.87 - 1) < 0.03
    assert "estimated intrinsics" in capsys.readouterr().out
