"""EXIF focal lengths: the tags read, both byte orders, resized images, and the use without K."""

import math
import struct

import pytest
import torch

import torchsfm
from torchsfm.io.datasets import read_strecha
from torchsfm.io.exif import exif_focal_pixels
from torchsfm.sfm.incremental import shared_focal


def tiff(entries: list[tuple[int, int, int, bytes]], order: str = "<") -> bytes:
    """A TIFF block whose IFD0 points to an EXIF IFD holding ``entries`` (tag, type, count,
    value bytes); values longer than 4 bytes go after the directories."""
    exif_offset = 8 + 2 + 12 + 4
    data_offset = exif_offset + 2 + 12 * len(entries) + 4
    directory, data = struct.pack(order + "H", len(entries)), b""
    for tag, kind, count, value in entries:
        if len(value) <= 4:
            directory += struct.pack(order + "HHI", tag, kind, count) + value.ljust(4, b"\0")
        else:
            directory += struct.pack(order + "HHII", tag, kind, count, data_offset + len(data))
            data += value
    header = (b"II" if order == "<" else b"MM") + struct.pack(order + "HI", 42, 8)
    first = struct.pack(order + "H", 1) + struct.pack(order + "HHII", 0x8769, 4, 1, exif_offset) + b"\0" * 4
    return header + first + directory + b"\0" * 4 + data


def with_exif(jpeg: bytes, block: bytes) -> bytes:
    """The JPEG with an APP1 ``Exif`` segment holding ``block`` right after its SOI marker."""
    payload = b"Exif\0\0" + block
    return jpeg[:2] + b"\xff\xe1" + struct.pack(">H", len(payload) + 2) + payload + jpeg[2:]


def rational(value: float, order: str = "<") -> bytes:
    return struct.pack(order + "II", round(value * 1000), 1000)


@pytest.fixture
def jpeg(shared_data):
    return (shared_data / "strecha_fountain_P11" / "0000.jpg").read_bytes()


@pytest.mark.parametrize("order", ["<", ">"])
def test_35mm_equivalent_focal_length(tmp_path, jpeg, order):
    path = tmp_path / "a.jpg"
    path.write_bytes(with_exif(jpeg, tiff([(0xA405, 3, 1, struct.pack(order + "H", 50))], order)))
    assert exif_focal_pixels(path, 768, 512) == pytest.approx(50 * math.hypot(768, 512) / math.hypot(36, 24), rel=1e-12)


def test_focal_plane_resolution_rescaled_to_the_stored_width(tmp_path, jpeg):
    entries = [(0x920A, 5, 1, rational(7.5)), (0xA20E, 5, 1, rational(1000.0)), (0xA210, 3, 1, struct.pack("<H", 3)),
               (0xA002, 4, 1, struct.pack("<I", 3072))]
    path = tmp_path / "a.jpg"
    path.write_bytes(with_exif(jpeg, tiff(entries)))
    assert exif_focal_pixels(path, 768, 512) == pytest.approx(7.5 * 1000 / 10 * 768 / 3072, rel=1e-12)  # px per cm


def test_no_usable_focal_length(tmp_path, jpeg):
    path = tmp_path / "a.jpg"
    path.write_bytes(jpeg)
    assert exif_focal_pixels(path, 768, 512) is None  # no EXIF at all
    path.write_bytes(with_exif(jpeg, tiff([(0x920A, 5, 1, rational(7.5))])))
    assert exif_focal_pixels(path, 768, 512) is None  # mm without the sensor's resolution
    path.write_bytes(b"not an image")
    assert exif_focal_pixels(path, 768, 512) is None


def test_focal_lengths_are_shared_only_when_every_image_agrees():
    assert shared_focal([700.0, 701.0, 700.5]) == pytest.approx(700.5)
    assert shared_focal([700.0, 760.0]) is None  # two cameras or a zoom: estimate instead
    assert shared_focal([700.0, None]) is None


def test_reconstruct_without_K_starts_from_the_exif_focal_length(shared_data, tmp_path):
    """Three fountain views whose EXIF states a 35 mm equivalent of 34 mm, 5 % over the truth
    (33.6 mm): the model's focal length, refined by bundle adjustment from there, is within 1 %
    of the truth."""
    sequence = read_strecha(shared_data / "strecha_fountain_P11")
    true_focal = float(sequence.K[0, 0, 0])
    f35 = 1.04 * true_focal * math.hypot(36, 24) / math.hypot(768, 512)
    assert round(f35) == 34
    paths = []
    for k in range(3):
        path = tmp_path / f"{k}.jpg"
        path.write_bytes(with_exif(sequence.images[k].read_bytes(), tiff([(0xA405, 3, 1, struct.pack("<H", round(f35)))])))
        paths.append(path)
    messages = []
    model = torchsfm.reconstruct(paths, generator=torch.Generator().manual_seed(0), progress=messages.append)
    assert any("focal length from EXIF" in message for message in messages)
    assert model.num_views == 3
    assert abs(float(model.cameras.K[0, 0, 0]) / true_focal - 1) < 0.01


def test_images_of_two_sizes_without_K_take_each_views_K_from_its_exif(shared_data, tmp_path):
    """Fountain-P11 views 0-4 with views 1 and 3 at twice the size (1536 x 1024: a second
    camera), no K, every file recording its focal length (7.5 mm and the focal plane's
    resolution): each view gets the K of its own EXIF focal length with the principal point at
    its centre, held as given; every view registered, rotations within 0.1° of the truth (median;
    measured 0.055°, max 0.127°: the centre is 5 px from the true principal point). A file
    without the tag: refused, naming the sizes and what would do."""
    from PIL import Image

    from torchsfm.errors import InputError
    from torchsfm.evaluation import camera_errors

    sequence = read_strecha(shared_data / "strecha_fountain_P11")
    true_focal = float(sequence.K[0, 0, 0])
    paths = []
    for v in range(5):
        image = Image.open(sequence.images[v])
        scale = 2 if v in (1, 3) else 1
        if scale > 1:
            image = image.resize((768 * scale, 512 * scale), Image.Resampling.BICUBIC)
        path = tmp_path / f"{v}.jpg"
        image.save(path, quality=95)
        entries = [(0x920A, 5, 1, rational(7.5)), (0xA20E, 5, 1, rational(10 * true_focal * scale / 7.5)),
                   (0xA210, 3, 1, struct.pack("<H", 3)), (0xA002, 4, 1, struct.pack("<I", 768 * scale))]
        path.write_bytes(with_exif(path.read_bytes(), tiff(entries)))
        paths.append(path)
    messages = []
    model = torchsfm.reconstruct(paths, generator=torch.Generator().manual_seed(0), progress=messages.append)
    assert any("each view's K from its EXIF focal length" in message for message in messages)
    assert model.view_indices == list(range(5))
    for v in range(5):
        scale = 2 if v in (1, 3) else 1
        expected = torch.tensor([[true_focal * scale, 0, (768 * scale - 1) / 2], [0, true_focal * scale, (512 * scale - 1) / 2], [0, 0, 1]],
                                dtype=torch.float64)
        torch.testing.assert_close(model.cameras.K[v], expected, rtol=1e-5, atol=1e-3)
    errors = camera_errors(model.cameras.R, model.cameras.t, sequence.R[:5], sequence.t[:5])
    assert float(errors.rotation.median()) < 0.1 and float(errors.rotation.max()) < 0.2
    Image.open(sequence.images[2]).save(paths[2], quality=95)  # no EXIF
    with pytest.raises(InputError, match=r"different sizes \(.*\) need their intrinsics K \(or a focal length in every file's EXIF\)"):
        torchsfm.reconstruct(paths, generator=torch.Generator().manual_seed(0))


def test_a_zoom_without_K_takes_each_views_K_from_its_exif(shared_data, tmp_path):
    """Fountain-P11 views 0-4 with views 1 and 3 zoomed in twice (their centres at full size: one
    image size, two focal lengths), no K, each file's EXIF recording its focal length: the
    focal lengths disagree, so each view gets the K of its own, the principal point at the
    centre; every view registered, rotations within 0.3° (median; measured 0.062°, max 0.126°;
    with one focal length for all, estimated as without EXIF: 743.8 px, 1.6-5.3°)."""
    from PIL import Image

    from torchsfm.evaluation import camera_errors

    sequence = read_strecha(shared_data / "strecha_fountain_P11")
    true_focal = float(sequence.K[0, 0, 0])
    paths, messages = [], []
    for v in range(5):
        image = Image.open(sequence.images[v])
        zoom = 2 if v in (1, 3) else 1
        if zoom > 1:
            image = image.crop((192, 128, 576, 384)).resize((768, 512), Image.Resampling.BICUBIC)
        path = tmp_path / f"{v}.jpg"
        image.save(path, quality=95)
        entries = [(0x920A, 5, 1, rational(7.5)), (0xA20E, 5, 1, rational(10 * true_focal * zoom / 7.5)),
                   (0xA210, 3, 1, struct.pack("<H", 3)), (0xA002, 4, 1, struct.pack("<I", 768))]
        path.write_bytes(with_exif(path.read_bytes(), tiff(entries)))
        paths.append(path)
    model = torchsfm.reconstruct(paths, generator=torch.Generator().manual_seed(0), progress=messages.append)
    assert any("EXIF focal lengths more than 1 % apart" in message for message in messages)
    assert model.view_indices == list(range(5))
    focal = model.cameras.K[:, 0, 0]
    torch.testing.assert_close(focal, true_focal * torch.tensor([1.0, 2, 1, 2, 1], dtype=torch.float64), rtol=1e-5, atol=0)
    errors = camera_errors(model.cameras.R, model.cameras.t, sequence.R[:5], sequence.t[:5])
    assert float(errors.rotation.median()) < 0.3


def test_a_portrait_shot_with_the_same_exif_focal_length_is_refined_with_the_others(shared_data, tmp_path):
    """Fountain-P11 views 0-4, view 2 turned to portrait, every file recording the same focal
    length 3 % over the truth: one camera, so the EXIF value starts one shared focal length that
    bundle adjustment refines (within 1 % of the truth), each view's principal point at its
    image's centre."""
    from PIL import Image

    sequence = read_strecha(shared_data / "strecha_fountain_P11")
    true_focal = float(sequence.K[0, 0, 0])
    paths, messages = [], []
    for v in range(5):
        image = Image.open(sequence.images[v])
        if v == 2:
            image = image.transpose(Image.Transpose.ROTATE_270)  # a quarter turn clockwise: 512 x 768
        path = tmp_path / f"{v}.jpg"
        image.save(path, quality=95)
        width = image.size[0]
        entries = [(0x920A, 5, 1, rational(7.5)), (0xA20E, 5, 1, rational(10 * 1.03 * true_focal / 7.5)),
                   (0xA210, 3, 1, struct.pack("<H", 3)), (0xA002, 4, 1, struct.pack("<I", width))]
        path.write_bytes(with_exif(path.read_bytes(), tiff(entries)))
        paths.append(path)
    model = torchsfm.reconstruct(paths, generator=torch.Generator().manual_seed(0), progress=messages.append)
    assert any("focal length from EXIF" in message for message in messages)
    assert model.view_indices == list(range(5))
    assert abs(float(model.cameras.K[0, 0, 0]) / true_focal - 1) < 0.01
    assert bool((model.cameras.K[:, 0, 0] == model.cameras.K[0, 0, 0]).all())
    torch.testing.assert_close(model.cameras.K[2, :2, 2], torch.tensor([255.5, 383.5], dtype=torch.float64), rtol=0, atol=1e-9)
