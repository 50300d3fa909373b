"""Readers for the ground-truth data sets in ``../shared/data`` (formats in each PROVENANCE.md)."""

from __future__ import annotations

from dataclasses import dataclass, replace
from pathlib import Path

import torch
from torch import Tensor

from torchsfm.camera import decompose_projection
from torchsfm.errors import InputError
from torchsfm.geometry.fundamental import fundamental_from_pose


def _read_matrix(path: Path) -> Tensor:
    """Whitespace-separated numbers, one row per line -> float64 (rows, columns)."""
    try:
        rows = [[float(value) for value in line.split()] for line in path.read_text().splitlines() if line.strip()]
    except (OSError, ValueError) as error:
        raise InputError(f"cannot read numeric table {path}: {error}") from None
    return torch.tensor(rows, dtype=torch.float64)


def _read_tracks(path: Path) -> Tensor:
    """Oxford n-view match table: one row per 3-D point, '*' for unseen -> int64 (M, V), -1 unseen."""
    try:
        rows = [[-1 if value == "*" else int(value) for value in line.split()] for line in path.read_text().splitlines() if line.strip()]
    except (OSError, ValueError) as error:
        raise InputError(f"cannot read match table {path}: {error}") from None
    return torch.tensor(rows, dtype=torch.long)


@dataclass
class OxfordMultiView:
    """An Oxford VGG multi-view data set (Model House, Merton College I, ...).

    Fields:
        P: (V, 3, 4) ground-truth cameras (pixels; x ~ P [X; 1]).
        corners: V tensors (n_v, 2) of corner positions (pixels, top-left pixel centre = (0, 0)).
        tracks: (M, V) int64 corner index of 3-D point m in view v, -1 where unseen.
        points3d: (M, 3) ground-truth 3-D points.
        images: image paths (empty where the set ships none).
    """

    P: Tensor
    corners: list[Tensor]
    tracks: Tensor
    points3d: Tensor
    images: list[Path]

    @property
    def num_views(self) -> int:
        return self.P.shape[0]

    def cameras(self) -> tuple[Tensor, Tensor, Tensor]:
        """K (V, 3, 3), R (V, 3, 3), t (V, 3) decomposed from P (see
        :func:`~torchsfm.camera.decompose_projection`; Model House's frame is mirrored, det R = -1)."""
        return decompose_projection(self.P)

    def relative_pose(self, i: int, j: int) -> tuple[Tensor, Tensor]:
        """Ground-truth pose of view j relative to view i: proper rotation (3, 3), unit t (3,)."""
        _, R, t = self.cameras()
        R_relative = R[j] @ R[i].transpose(-1, -2)
        t_relative = t[j] - R_relative @ t[i]
        return R_relative, t_relative / t_relative.norm()

    def correspondences(self, i: int, j: int) -> tuple[Tensor, Tensor]:
        """Ground-truth matches between views i and j: two (K, 2) pixel tensors."""
        both = (self.tracks[:, i] >= 0) & (self.tracks[:, j] >= 0)
        return self.corners[i][self.tracks[both, i]], self.corners[j][self.tracks[both, j]]


def read_oxford_multiview(folder: str | Path) -> OxfordMultiView:
    """Read an Oxford VGG multi-view folder (``2D/*.corners``, ``*.P`` in 2D/ or 3D/,
    ``2D/*nview-corners``, ``3D/*p3d``, optional ``images/``)."""
    folder = Path(folder)
    corner_files = sorted((folder / "2D").glob("*.corners"))
    P_files = sorted(folder.glob("[23]D/*.P"))
    track_files = sorted((folder / "2D").glob("*nview-corners"))
    point_files = sorted((folder / "3D").glob("*p3d"))
    if not corner_files or len(P_files) != len(corner_files) or len(track_files) != 1 or len(point_files) != 1:
        raise InputError(f"{folder} is not an Oxford VGG multi-view folder (need 2D/*.corners, *.P per view, "
                         "2D/*nview-corners, 3D/*p3d)")
    return OxfordMultiView(
        P=torch.stack([_read_matrix(path) for path in P_files]),
        corners=[_read_matrix(path) for path in corner_files],
        tracks=_read_tracks(track_files[0]),
        points3d=_read_matrix(point_files[0]),
        images=sorted((folder / "images").glob("*.jpg")),
    )


@dataclass
class StrechaSequence:
    """A Strecha multi-view set as prepared in ``../shared/data`` (768×512 JPEGs, one ``.txt`` per image).

    Fields:
        images: V image paths, in file order.
        K: (V, 3, 3) intrinsics; R: (V, 3, 3) and t: (V, 3) camera from world (x_cam = R X + t).
    """

    images: list[Path]
    K: Tensor
    R: Tensor
    t: Tensor

    def relative_pose(self, i: int, j: int) -> tuple[Tensor, Tensor]:
        """Ground-truth pose of view j relative to view i: rotation (3, 3), unit t (3,)."""
        R_relative = self.R[j] @ self.R[i].transpose(-1, -2)
        t_relative = self.t[j] - R_relative @ self.t[i]
        return R_relative, t_relative / t_relative.norm()


def _camera_tables(cameras: list[Path]) -> Tensor:
    """(V, 7, 3) K, R, t tables of Strecha-layout camera files (7 rows of 3 numbers, '#' comments)."""
    tables = []
    for path in cameras:
        lines = [line for line in path.read_text().splitlines() if line.strip() and not line.lstrip().startswith("#")]
        try:
            table = torch.tensor([[float(v) for v in line.split()] for line in lines], dtype=torch.float64)
        except ValueError as error:
            raise InputError(f"cannot read camera file {path}: {error}") from None
        if table.shape != (7, 3):
            raise InputError(f"camera file {path} must hold 7 rows of 3 numbers (K, R, t), got {tuple(table.shape)}")
        tables.append(table)
    return torch.stack(tables)


def _sequence(images: list[Path], cameras: list[Path]) -> StrechaSequence:
    missing = [str(path) for path in images if not path.exists()]
    if missing:
        raise InputError(f"missing images for camera files: {', '.join(missing)}")
    tables = _camera_tables(cameras)
    return StrechaSequence(images=images, K=tables[:, :3], R=tables[:, 3:6], t=tables[:, 6])


def read_strecha(folder: str | Path) -> StrechaSequence:
    """Read ``NNNN.jpg`` + ``NNNN.txt`` pairs (K, R, t as 7 rows of 3 numbers, '#' comments)."""
    folder = Path(folder)
    cameras = sorted(folder.glob("[0-9]*.txt"))
    if not cameras:
        raise InputError(f"{folder} holds no Strecha camera files (NNNN.txt)")
    return _sequence([path.with_suffix(".jpg") for path in cameras], cameras)


def read_kitti_odometry(folder: str | Path) -> StrechaSequence:
    """A KITTI odometry excerpt laid out as ``image_0/NNNNNN.png`` + ``cameras/NNNNNN.txt`` (the
    Strecha layout, camera from world; ``kitti_odom_seq06_000-050/PROVENANCE.md``)."""
    folder = Path(folder)
    cameras = sorted((folder / "cameras").glob("[0-9]*.txt"))
    if not cameras:
        raise InputError(f"{folder}/cameras holds no camera files (NNNNNN.txt)")
    return _sequence([folder / "image_0" / path.with_suffix(".png").name for path in cameras], cameras)


@dataclass
class GroundTruthPair:
    """Two images with ground-truth intrinsics and relative pose (camera 2 from camera 1, unit t)."""

    name: str
    image1: Path
    image2: Path
    K1: Tensor
    K2: Tensor
    R: Tensor
    t: Tensor

    @property
    def F(self) -> Tensor:
        """The ground-truth fundamental matrix (unit norm)."""
        return fundamental_from_pose(self.K1, self.K2, self.R, self.t)


def ground_truth_pairs(data: str | Path) -> list[GroundTruthPair]:
    """The evaluation pairs of ``../shared/data``: every neighbouring pair of Strecha fountain-P11 and
    Herz-Jesu-P8, and the pairs (0, 1), (1, 2), (0, 2) of Oxford Merton College I."""
    data = Path(data)
    pairs = []
    for name in ("strecha_fountain_P11", "strecha_herzjesu_P8"):
        sequence = read_strecha(data / name)
        for i in range(len(sequence.images) - 1):
            pairs.append(GroundTruthPair(f"{name} {i}-{i + 1}", sequence.images[i], sequence.images[i + 1],
                                         sequence.K[i], sequence.K[i + 1], *sequence.relative_pose(i, i + 1)))
    merton = read_oxford_multiview(data / "oxford_merton1")
    K, _, _ = merton.cameras()
    for i, j in ((0, 1), (1, 2), (0, 2)):
        pairs.append(GroundTruthPair(f"oxford_merton1 {i}-{j}", merton.images[i], merton.images[j], K[i], K[j], *merton.relative_pose(i, j)))
    return pairs


# Which Hopkins155 motion group is the static background. The labels are motion groups, not
# background flags; checked by overlaying the tracks on each preview.jpg: the trees of cars1 and
# truck1 (their tracks' y axis points up: 480 - y overlays the preview), the parking lot of
# kanatani1, the room around the two checkerboard objects of 1R2RC, and the trees and traffic
# light of cars8 (its frame 0 is the preview, y up: group 1 lies on the trees, group 2 on the
# SUV that crosses — the one traffic sequence of hopkins155_dev where the highest label is not
# the background; cars2B, cars4, cars6, cars10, people1 and kanatani2 follow the convention).
HOPKINS_BACKGROUND_GROUP = {"cars1": 2, "truck1": 2, "kanatani1": 1, "1R2RC": 3, "cars8": 1}


FRAME_CUTS = {  # MotionTracks.cut: frame count -> the frames kept
    "all": torch.arange,
    "first-half": lambda count: torch.arange(max(count // 2, 3)),  # a shorter sequence, less motion between its ends
    "every-other": lambda count: torch.arange(0, count, 2),  # half the frame rate
}


@dataclass
class MotionTracks:
    """Points tracked over F frames with per-point motion labels.

    Fields:
        name: the sequence.
        tracks: (F, N, 2) float64 pixel positions as stored (0 where not visible).
        labels: (N,) int64: 0 the static background, 1, 2, ... the moving objects.
        image_size: (width, height).
        visible: (F, N) bool, where each track is seen (all True for Hopkins155).
        has_outliers: whether ``labels`` marks gross outliers with -1 (AdelaideRMF).
    """

    name: str
    tracks: Tensor
    labels: Tensor
    image_size: tuple[int, int]
    visible: Tensor | None = None
    has_outliers: bool = False

    def __post_init__(self) -> None:
        if self.visible is None:
            self.visible = torch.ones(self.tracks.shape[:2], dtype=torch.bool)

    def with_noise(self, sigma: float, seed: int = 0) -> MotionTracks:
        """The sequence with Gaussian noise of ``sigma`` px (seeded by ``seed``) added to each
        coordinate of every visible position: the view of a noisier tracker, for robustness
        checks (Hopkins155's tracks lie 0.05-0.2 px from one F per frame pair)."""
        noise = sigma * torch.randn(self.tracks.shape, generator=torch.Generator().manual_seed(seed), dtype=self.tracks.dtype)
        return replace(self, tracks=torch.where(self.visible[..., None], self.tracks + noise, self.tracks))

    def subset(self, share: float, seed: int = 0) -> MotionTracks:
        """The sequence with each track kept with probability ``share`` (seeded by ``seed``): the
        view of a sparser tracker, with fewer tracks on every motion, for robustness checks."""
        if not 0 < share <= 1:
            raise InputError(f"share must lie in (0, 1], got {share}")
        kept = torch.rand(self.labels.numel(), generator=torch.Generator().manual_seed(seed)) < share
        return replace(self, tracks=self.tracks[:, kept], labels=self.labels[kept], visible=self.visible[:, kept])

    def cut(self, frames: str) -> MotionTracks:
        """The sequence on the frames ``frames`` names (:data:`FRAME_CUTS`: ``all``, ``first-half``
        — at least 3 —, ``every-other``; :meth:`on_frames`); two views stay as they are, and a cut
        that leaves fewer than 3 frames is an InputError."""
        if frames not in FRAME_CUTS:
            raise InputError(f"frames must be one of {sorted(FRAME_CUTS)}, got {frames!r}")
        if frames == "all" or self.tracks.shape[0] <= 2:
            return self
        kept = FRAME_CUTS[frames](self.tracks.shape[0])
        if kept.numel() < 3:
            raise InputError(f"{self.name}: {frames} of its {self.tracks.shape[0]} frames leaves {kept.numel()}, fewer than 3")
        return self.on_frames(kept)

    def on_frames(self, frames: Tensor, min_seen: int = 3) -> MotionTracks:
        """The sequence on the (F',) ``frames`` only (indices, in that order), keeping the tracks
        seen in at least ``min_seen`` of them (the others could not be judged): a shorter
        sequence or a lower frame rate, for robustness checks."""
        frames = torch.as_tensor(frames, dtype=torch.long)
        visible = self.visible[frames]
        kept = visible.sum(0) >= min_seen
        return replace(self, tracks=self.tracks[frames][:, kept], labels=self.labels[kept], visible=visible[:, kept])


def _load_mat(path: Path) -> dict:
    """A MATLAB v5 file (needs SciPy)."""
    try:
        from scipy.io import loadmat
    except ImportError as error:
        raise InputError("reading MATLAB .mat files needs SciPy: pip install scipy") from error
    return loadmat(path)


def _relabel(groups: Tensor, background: int) -> Tensor:
    """Motion groups (N,) -> 0 for the background group, 1, 2, ... for the others in order."""
    objects = torch.unique(groups[groups != background])
    labels = torch.zeros_like(groups)
    for k, group in enumerate(objects.tolist(), start=1):
        labels[groups == group] = k
    return labels


def read_hopkins155(folder: str | Path) -> MotionTracks:
    """A Hopkins155 sequence folder ``<name>/<name>_truth.mat`` (needs SciPy to read MATLAB files).

    Uses the pixel tracks ``y`` (not ``x``, which is normalized by a matrix that is not the
    camera's K). Groups are relabelled so that 0 is the background (see
    :data:`HOPKINS_BACKGROUND_GROUP`); for another sequence the highest label is taken, as the
    database's convention for a moving camera (``hopkins155_dev/PROVENANCE.md``).
    """
    folder = Path(folder)
    path = folder / f"{folder.name}_truth.mat"
    if not path.is_file():
        raise InputError(f"no Hopkins155 ground truth {path}")
    mat = _load_mat(path)
    y = torch.from_numpy(mat["y"].astype("float64"))  # (3, N, F) homogeneous pixels
    tracks = (y[:2] / y[2:]).permute(2, 1, 0).contiguous()
    groups = torch.from_numpy(mat["s"].astype("int64")).flatten()
    labels = _relabel(groups, HOPKINS_BACKGROUND_GROUP.get(folder.name, int(groups.max())))
    return MotionTracks(name=folder.name, tracks=tracks, labels=labels,
                        image_size=(int(mat["width"].item()), int(mat["height"].item())))


def read_kt3dmoseg(folder: str | Path) -> MotionTracks:
    """A KT3DMoSeg clip folder ``<clip>_Tracks/<clip>_Tracks.mat`` (needs SciPy): the labelled
    tracks ``ySparse`` with their visibility; the largest motion group is the background
    (``kt3dmoseg_dev/PROVENANCE.md``). KITTI images are about 1242×375."""
    folder = Path(folder)
    path = folder / f"{folder.name}.mat"
    if not path.is_file():
        raise InputError(f"no KT3DMoSeg tracks {path}")
    data = _load_mat(path)["Data"][0, 0]
    y = torch.from_numpy(data["ySparse"].astype("float64"))  # (3, N, F)
    visible = torch.from_numpy(data["visibleSparse"].astype(bool)).T.contiguous()  # (F, N)
    tracks = (y[:2] / torch.where(y[2:] != 0, y[2:], 1.0)).permute(2, 1, 0)
    tracks = torch.where(visible[..., None], tracks, 0.0).contiguous()
    groups = torch.from_numpy(data["GtLabel"].astype("int64")).flatten()
    labels = _relabel(groups, int(torch.bincount(groups).argmax()))
    return MotionTracks(name=folder.name.removesuffix("_Tracks"), tracks=tracks, labels=labels, image_size=(1242, 375),
                        visible=visible)


def read_adelaidermf(path: str | Path) -> MotionTracks:
    """An AdelaideRMF fundamental-matrix scene ``<scene>.mat`` (needs SciPy) as two-frame tracks:
    the matches (2, N, 2) in pixels (MATLAB's 1-based origin moved to 0), labels 0, 1, ... for
    the rigid structures in the order stored and -1 for the gross outliers
    (``adelaidermf_F/PROVENANCE.md``). Structure 0 is not a "static scene": two views of
    independently moved objects have none."""
    path = Path(path)
    if not path.is_file():
        raise InputError(f"no AdelaideRMF scene {path}")
    mat = _load_mat(path)
    data = torch.from_numpy(mat["data"].astype("float64"))  # (6, N)
    tracks = torch.stack([data[0:2].T, data[3:5].T]) - 1.0
    labels = torch.from_numpy(mat["label"].astype("int64")).flatten() - 1
    height, width = mat["img1"].shape[:2]
    return MotionTracks(name=path.stem, tracks=tracks.contiguous(), labels=labels, image_size=(int(width), int(height)),
                        has_outliers=True)
