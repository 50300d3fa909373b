"""Ground truth for tests, examples and benchmarks: seeded synthetic scenes (:mod:`.scenes`),
rendered images (:mod:`.rendering`) and scored runs on real data sets (:mod:`.runners`); the
measures themselves live in :mod:`torchsfm.evaluation` (re-exported here)."""

from torchsfm.evaluation import mask_recall_precision, rejection_figures, rotation_error_deg, translation_direction_error_deg
from torchsfm.testing.rendering import (PATCH_POSITIONS, insert_moving_patch, inside_boxes, random_squares, render_chessboard,
                                        patch_coordinates, render_corner_scene, render_squares, square_corners)
from torchsfm.testing.runners import InsertedObjectTriplet, evaluate_two_view_pair, inserted_object_triplet, match_triplet
from torchsfm.testing.scenes import (MovingObjectScene, TwoViewScene, board_poses, look_at_rotation, replace_with_random_points,
                                     sliding_plane_scene, synthetic_moving_scene, synthetic_two_view, visible_board_poses, wide_angle_camera)

__all__ = [
    "PATCH_POSITIONS", "InsertedObjectTriplet", "MovingObjectScene", "TwoViewScene", "board_poses", "evaluate_two_view_pair",
    "insert_moving_patch", "inserted_object_triplet", "inside_boxes", "look_at_rotation", "mask_recall_precision",
    "match_triplet", "patch_coordinates", "random_squares", "rejection_figures", "render_chessboard", "render_corner_scene", "render_squares",
    "replace_with_random_points", "rotation_error_deg", "sliding_plane_scene", "square_corners", "synthetic_moving_scene", "synthetic_two_view",
    "translation_direction_error_deg", "visible_board_poses", "wide_angle_camera",
]
