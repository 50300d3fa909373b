"""The result type of every reconstruction: cameras, 3-D points, colours and observations."""

from __future__ import annotations

from dataclasses import dataclass, field

import torch
from torch import Tensor

from torchsfm.camera import Camera
from torchsfm.moving.imor import MovingObjectRejection


@dataclass
class Reconstruction:
    """A sparse model.

    Fields:
        cameras: :class:`~torchsfm.camera.Camera` batch, K (V, 3, 3), R (V, 3, 3), t (V, 3),
            camera from world (the world frame is camera 0's for a two-view model).
        image_names: V names (file names where known).
        image_sizes: (V, 2) int64 (width, height).
        points3d: (P, 3) float64 world points.
        colors: (P, 3) uint8 RGB.
        observation_points: (O,) int64 index of the observed point.
        observation_views: (O,) int64 index of the observing view.
        keypoints: (O, 2) float64 observed pixels.
        matches: two-view models only: (M, 4) putative matches (x1, y1, x2, y2), else None.
        inlier_mask: two-view models only: (M,) bool, the matches kept by the geometry.
        view_indices: the input index of every view of the model (registered views).
        unregistered: input views left out of the model, with the reason.
        loose_resections: multi-view models only: input views whose resection kept too few
            inliers at ``resection.ransac.inlier_threshold`` and registered at a wider threshold
            (px; see :func:`torchsfm.sfm.mapping.resect`): less certain than the others.
        tracked_resections: multi-view models only: input views whose resection kept too few
            inliers at ``resection.ransac.inlier_threshold`` and that were registered by
            tracking against the map (:func:`torchsfm.sfm.mapping.pose_by_tracking`: the model's
            points searched where the pose of a widened threshold puts them, the view resected
            again at the threshold from what was found), with that resection's inliers.
        still_frames: multi-view models only: input views whose camera did not move from an
            earlier keyframe (``{view: keyframe}``, :func:`torchsfm.sfm.mapping.still_frames`):
            resected from the final model, not bundle-adjusted.
        timings: seconds per pipeline stage.
        moving_objects: with moving-object rejection on, IMOR + RANSAC's result for every frame
            triplet (input view indices, the middle one the reference); its vectors are the
            two-view model's matches seen in all three frames, or the multi-view model's tracks
            seen in all three.
        moving_rejections_per_view: multi-view models with the rejection on: per input view, its
            track observations rejected as moving (or untestable) by the whole-track decision.
        point_tracks: multi-view models only: (P,) int64, the track each point triangulates
            (the input track index for :func:`~torchsfm.sfm.from_tracks.reconstruct_tracks`).
        other_models: multi-view models only: the separate models of views this model could not
            reach (the set split), largest first, each with its own ``view_indices`` (input views)
            and frame; empty when every reconstructed view is in this one.
        objects: with ``moving_objects.reconstruct_objects``: every independently moving body
            the segmentation found (:class:`MovingObject`), with its model or why it has none.
        segmented_tracks: with ``moving_objects.reconstruct_objects``: every track's (V, T, 2)
            undistorted pixels and (V, T) visibility over the views read, and its final (T,)
            label (0 the scene, k a body, -1 none) — what ``segmentation.png`` draws.
    """

    cameras: Camera
    image_names: list[str]
    image_sizes: Tensor
    points3d: Tensor
    colors: Tensor
    observation_points: Tensor
    observation_views: Tensor
    keypoints: Tensor
    matches: Tensor | None = None
    inlier_mask: Tensor | None = None
    view_indices: list[int] = field(default_factory=list)
    unregistered: dict[int, str] = field(default_factory=dict)
    loose_resections: dict[int, float] = field(default_factory=dict)
    tracked_resections: dict[int, int] = field(default_factory=dict)
    still_frames: dict[int, int] = field(default_factory=dict)
    timings: dict[str, float] = field(default_factory=dict)
    moving_objects: dict[tuple[int, int, int], MovingObjectRejection] = field(default_factory=dict)
    moving_rejections_per_view: dict[int, int] = field(default_factory=dict)
    point_tracks: Tensor | None = None
    other_models: list[Reconstruction] = field(default_factory=list)
    objects: list[MovingObject] = field(default_factory=list)
    segmented_tracks: tuple[Tensor, Tensor, Tensor] | None = None

    @property
    def num_views(self) -> int:
        return self.cameras.K.shape[0]

    @property
    def num_points(self) -> int:
        return self.points3d.shape[0]

    def observation_errors(self) -> Tensor:
        """Reprojection error (pixels) of every observation: (O,)."""
        views = self.observation_views
        camera = Camera(self.cameras.K[views], self.cameras.R[views], self.cameras.t[views], self.cameras.distortion[views])
        projected = camera.project(self.points3d[self.observation_points][:, None])[:, 0]
        return (projected - self.keypoints).norm(dim=-1)

    def point_errors(self) -> Tensor:
        """Per-point RMS reprojection error over its observations (pixels): (P,)."""
        squared = torch.zeros(self.num_points, dtype=self.points3d.dtype).index_add_(0, self.observation_points, self.observation_errors() ** 2)
        counts = torch.bincount(self.observation_points, minlength=self.num_points).clamp_min(1)
        return (squared / counts).sqrt()

    def reprojection_rms(self) -> float:
        """RMS reprojection error over all observations (pixels)."""
        errors = self.observation_errors()
        return float(errors.square().mean().sqrt()) if errors.numel() else 0.0


@dataclass
class MovingObject:
    """One independently moving rigid body of a multi-view reconstruction.

    Fields:
        label: its motion label (1..k) in the segmentation of the tracks.
        num_tracks: the tracks the segmentation gave it.
        model: the body in its own frame — its points, and per frame it is seen in the camera's
            pose relative to the body (``view_indices``: input views) — or None.
        reason: why there is no model (too few tracks or frames, no baseline), else "".

    The body's scale is its own: unknown relative to the scene's (a body moving along the
    camera's line of sight at a constant speed is as consistent with a nearer, static one).
    :meth:`poses_in_scene` places it in the scene's frame for a chosen scale;
    :meth:`steady_trajectory` chooses the one under which it moves most steadily.
    """

    label: int
    num_tracks: int
    model: Reconstruction | None = None
    reason: str = ""

    def poses_in_scene(self, scene: Reconstruction, scale: float = 1.0) -> tuple[list[int], Tensor, Tensor]:
        """The body's pose in the scene's frame in every input view both models registered:
        (view indices, (n, 3, 3) world-from-body rotations, (n, 3) positions of the body's origin),
        its translations multiplied by ``scale`` (the body's size in scene units per model unit).
        The rotations do not depend on the scale."""
        views, rotations, origins, per_scale = self._in_scene(scene)
        return views, rotations, origins + scale * per_scale

    def _in_scene(self, scene: Reconstruction) -> tuple[list[int], Tensor, Tensor, Tensor]:
        """Views both models registered, world-from-body rotations (n, 3, 3), and the body
        origin's positions (n, 3) at scale 0 and their change per unit of scale."""
        if self.model is None:
            empty = torch.empty(0, 3, dtype=torch.float64)
            return [], torch.empty(0, 3, 3, dtype=torch.float64), empty, empty
        in_scene = {v: k for k, v in enumerate(scene.view_indices)}
        pairs = [(v, in_scene[v], k) for k, v in enumerate(self.model.view_indices) if v in in_scene]
        views = [v for v, _, _ in pairs]
        scene_camera = torch.tensor([s for _, s, _ in pairs], dtype=torch.long)
        body_camera = torch.tensor([b for _, _, b in pairs], dtype=torch.long)
        R_scene, t_scene = scene.cameras.R[scene_camera], scene.cameras.t[scene_camera]  # camera from world
        R_body, t_body = self.model.cameras.R[body_camera], self.model.cameras.t[body_camera]  # camera from body
        to_world = R_scene.transpose(1, 2)
        return views, to_world @ R_body, -(to_world @ t_scene[..., None])[..., 0], (to_world @ t_body[..., None])[..., 0]

    def placed_in_scene(self, scene: Reconstruction) -> tuple[Tensor, Tensor, float] | None:
        """The body's points in the scene's frame at its first shared view, scaled by
        :meth:`steady_trajectory`, and that point's path: ((P, 3) points, (n, 3) path, scale), or
        None where the steady-motion scale is undetermined."""
        steady = self.steady_trajectory(scene)
        if steady is None:
            return None
        scale, _, path = steady
        _, rotations, positions = self.poses_in_scene(scene, scale)
        return (scale * self.model.points3d) @ rotations[0].T + positions[0], path, scale

    def steady_trajectory(self, scene: Reconstruction) -> tuple[float, list[int], Tensor] | None:
        """The scale (scene units per model unit) under which some point of the body moves with the
        least acceleration through the scene over evenly spaced views, and that point's path: (s,
        views, (n, 3) positions in the scene's frame). A prior (cars and people move steadily),
        exact for a body turning steadily about a point that moves at constant velocity; second
        differences amplify noise, so it needs many views (measured: exact without noise over 5
        frames, unusable with 0.3 px noise over 5). A body point u (model units times s) is at
        X_f = a_f + R_f u + s d_f in view f (:meth:`poses_in_scene`: a_f the positions at scale
        0, R_f the rotations, d_f the positions' change per unit of scale), linear in (u, s):
        least squares on Δ²X = 0 over every evenly spaced view triple (a steady turn leaves u free
        along its axis, which does not touch s). None when fewer than two such triples are shared,
        when s is not determined (e.g. the camera and the body both moving steadily: every scale
        is as smooth) or when s ≤ 0."""
        views, rotations, origins, per_scale = self._in_scene(scene)
        if len(views) < 4:
            return None
        index = torch.tensor(views)
        even = torch.nonzero(index[2:] - index[1:-1] == index[1:-1] - index[:-2]).flatten()
        if even.numel() < 2:
            return None
        rotation_change, scale_change, origin_change = (
            p[even + 2] - 2 * p[even + 1] + p[even] for p in (rotations, per_scale, origins))
        system = torch.cat([rotation_change, scale_change[..., None]], dim=-1).reshape(-1, 4)  # rows of Δ²X = 0 in (u, s)
        _, singular, Vh = torch.linalg.svd(system, full_matrices=False)
        weak = singular <= 1e-6 * singular[0]  # a steady turn leaves u free along its axis: harmless unless s is free too
        if bool((Vh[weak, 3].abs() > 1e-2).any()):
            return None
        solution = torch.linalg.pinv(system) @ -origin_change.reshape(-1)
        scale = float(solution[3])
        if scale <= 0:
            return None
        return scale, views, origins + rotations @ solution[:3] + scale * per_scale
