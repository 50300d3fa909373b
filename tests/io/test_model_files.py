import pytest
import torch
from torch.testing import assert_close

from torchsfm.actions import reconstruction_files, reconstruction_summary
from torchsfm.camera import Camera
from torchsfm.config import Config
from torchsfm.errors import InputError
from torchsfm.io.atomic import atomic_write_text
from torchsfm.io.colmap import read_colmap_text, write_colmap_text
from torchsfm.io.ply import write_ply
from torchsfm.io.vrml import vrml_text, write_vrml
from torchsfm.reconstruction import MovingObject, Reconstruction
from torchsfm.testing import synthetic_two_view
from torchsfm.visualization import MOTION_COLOURS


def _model(distortion=(0.0, 0.0)):
    scene = synthetic_two_view(40, seed=0)
    P = 40
    index = torch.arange(P)
    cameras = Camera(K=torch.stack([scene.K1, scene.K2]), R=torch.stack([torch.eye(3, dtype=torch.float64), scene.R]),
                     t=torch.stack([torch.zeros(3, dtype=torch.float64), scene.t]),
                     distortion=torch.tensor([distortion, distortion], dtype=torch.float64))
    return Reconstruction(
        cameras=cameras, image_names=["a.jpg", "b.jpg"], image_sizes=torch.tensor([[640, 480], [640, 480]]),
        points3d=scene.points3d, colors=torch.randint(0, 256, (P, 3), generator=torch.Generator().manual_seed(0)).to(torch.uint8),
        observation_points=torch.cat([index, index]), observation_views=torch.cat([torch.zeros(P, dtype=torch.long), torch.ones(P, dtype=torch.long)]),
        keypoints=torch.cat([scene.x1, scene.x2]),
    )


def test_reprojection_errors_of_an_exact_model_vanish():
    model = _model()
    assert model.reprojection_rms() < 1e-9 and model.point_errors().shape == (40,)


def test_ply_opens_with_plyfile(tmp_path):
    plyfile = pytest.importorskip("plyfile", reason="plyfile is in the dev extra")
    model = _model()
    write_ply(tmp_path / "points.ply", model.points3d, model.colors)
    vertices = plyfile.PlyData.read(tmp_path / "points.ply")["vertex"]
    assert vertices.count == 40
    assert_close(torch.tensor(vertices["x"].tolist(), dtype=torch.float64), model.points3d[:, 0], rtol=1e-6, atol=1e-6)
    assert vertices["red"].tolist() == model.colors[:, 0].tolist()


@pytest.mark.parametrize("distortion", [(0.0, 0.0), (-0.1, 0.02)])
def test_colmap_text_round_trip(tmp_path, distortion):
    model = _model(distortion)
    write_colmap_text(tmp_path, model)
    back = read_colmap_text(tmp_path)
    assert back.image_names == model.image_names
    assert_close(back.cameras.K, model.cameras.K, rtol=0, atol=1e-12)
    assert_close(back.cameras.R, model.cameras.R, rtol=0, atol=1e-12)
    assert_close(back.cameras.t, model.cameras.t, rtol=0, atol=1e-12)
    assert_close(back.cameras.distortion, model.cameras.distortion)
    assert_close(back.points3d, model.points3d, rtol=0, atol=1e-12)
    assert torch.equal(back.colors, model.colors)
    assert_close(back.keypoints, model.keypoints, rtol=0, atol=1e-8)
    assert torch.equal(back.observation_points, model.observation_points)


def test_colmap_pixel_convention_and_pycolmap(tmp_path):
    model = _model()
    write_colmap_text(tmp_path, model)
    fields = (tmp_path / "cameras.txt").read_text().splitlines()[-1].split()
    assert fields[1] == "PINHOLE" and float(fields[6]) == pytest.approx(float(model.cameras.K[0, 0, 2]) + 0.5)
    pycolmap = pytest.importorskip("pycolmap", reason="pycolmap is in the bench extra")
    reconstruction = pycolmap.Reconstruction(str(tmp_path))
    assert reconstruction.num_points3D() == 40 and reconstruction.num_reg_images() == 2
    assert reconstruction.compute_mean_reprojection_error() < 1e-6


def test_colmap_refuses_skew(tmp_path):
    model = _model()
    model.cameras.K[0, 0, 1] = 2.0
    with pytest.raises(InputError, match="skew"):
        write_colmap_text(tmp_path, model)
    assert not any(tmp_path.iterdir())  # nothing written


@pytest.mark.parametrize("file, edit, message", [
    ("cameras.txt", lambda text: text + "7 PINHOLE 640 480 abc 500 320 240\n", r"malformed line in COLMAP file .*cameras.txt: '7 PINHOLE"),
    ("cameras.txt", lambda text: text.replace("2 PINHOLE 640 480 600 612 320 240", "2 OPENCV 640 480 600 612 320 240 0.1 0 0.001 0"),
     r"camera 2 has tangential distortion \(p1, p2 = 0.001, 0\)"),
    ("images.txt", lambda text: text.replace(" 1 a.jpg", " 9 a.jpg"), r"malformed line .*images.txt: '1 1 0 0 0 0 0 0 9 a.jpg' \(KeyError: 9\)"),
    ("images.txt", lambda text: "", "holds no images"),
    ("points3D.txt", lambda text: "\n".join(text.splitlines()[:-1]) + "\n", "observes points missing from points3D.txt"),
])
def test_a_malformed_colmap_model_is_named(tmp_path, file, edit, message):
    """Each COLMAP file's damage is an InputError that names the file (before: ValueError,
    KeyError or a RuntimeError from an empty stack, and an OPENCV camera's tangential terms
    silently dropped)."""
    write_colmap_text(tmp_path, _model())
    path = tmp_path / file
    path.write_text(edit(path.read_text()))
    with pytest.raises(InputError, match=message):
        read_colmap_text(tmp_path)


def test_a_ply_refuses_what_a_viewer_would_choke_on(tmp_path):
    model = _model()
    with pytest.raises(InputError, match="points holds 3 NaN"):
        write_ply(tmp_path / "p.ply", torch.where(torch.arange(40)[:, None] == 5, float("nan"), model.points3d), model.colors)
    with pytest.raises(InputError, match="colors must be uint8"):
        write_ply(tmp_path / "p.ply", model.points3d, model.colors.float())
    assert not any(tmp_path.iterdir())


def test_vrml_holds_the_points_and_a_pyramid_per_camera(tmp_path):
    model = _model()
    text = vrml_text(model)
    assert text.startswith("#VRML V2.0 utf8")
    assert text.count("IndexedLineSet") == 2 and text.count("PointSet") == 1
    write_vrml(tmp_path / "m.wrl", model)
    assert (tmp_path / "m.wrl").read_text() == text


def test_atomic_write_leaves_no_temporary_file(tmp_path):
    atomic_write_text(tmp_path / "a.txt", "hello")
    assert [p.name for p in tmp_path.iterdir()] == ["a.txt"] and (tmp_path / "a.txt").read_text() == "hello"
    assert oct((tmp_path / "a.txt").stat().st_mode & 0o777) != oct(0o600)


def test_a_split_set_writes_each_other_model_in_its_own_folder():
    model = _model()
    model.other_models = [_model(), _model()]
    files = reconstruction_files(model, {"views_registered": 2})
    for folder in ("", "other_models/1/", "other_models/2/"):
        assert {f"{folder}model.wrl", f"{folder}points.ply", f"{folder}colmap/images.txt"} <= files.keys()
    assert "other_models/3/model.wrl" not in files and files["summary.json"].startswith("{")


def test_each_moving_body_with_a_model_gets_its_folder_and_a_summary_row():
    model = _model()
    model.objects = [MovingObject(label=1, num_tracks=80, model=_model()), MovingObject(label=3, num_tracks=12, reason="too few tracks")]
    summary = reconstruction_summary(model, 1.0, Config())
    assert summary["objects"][0]["folder"] == "objects/1" and summary["objects"][0]["reason"] is None
    assert summary["objects"][1] == {"label": 3, "tracks": 12, "reason": "too few tracks"}
    files = reconstruction_files(model, summary)
    assert {"objects/1/model.wrl", "objects/1/points.ply", "objects/1/colmap/images.txt"} <= files.keys()
    assert not any(name.startswith("objects/3/") for name in files) and "segmentation.png" not in files
    width, height = model.image_sizes[0].tolist()
    pixels = torch.tensor([[[10.0, 10.0], [50.0, 30.0]], [[12.0, 11.0], [60.0, 32.0]]], dtype=torch.float64)  # (V, T, 2)
    model.segmented_tracks = (pixels, torch.ones(2, 2, dtype=torch.bool), torch.tensor([0, 1]))
    figure = reconstruction_files(model, summary)["segmentation.png"]
    assert figure.shape == (3, height, width) and figure.dtype == torch.uint8
    assert tuple(figure[:, 32, 60].tolist()) == MOTION_COLOURS[1]  # body 1's last position, in its colour
