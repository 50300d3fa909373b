"""The thesis' comparison of §3.4: R, t from E by SVD, by the linear method and by quaternions.

For each noise level, 20 synthetic two-view scenes (200 points, no outliers) give an E through
the normalized 8-point algorithm (E = Kᵀ F K, no refinement); each decomposition, followed by the
cheirality test, yields R, t. Printed: the median rotation and translation-direction errors, for
E from the rank-2 F (the pipeline's) and from the raw linear F (rank 3 under noise, the case
where the methods differ: on a rank-2 E all three reduce to the same orthogonal Procrustes
answer once R is projected onto SO(3)).

    python examples/essential_methods.py
"""

from __future__ import annotations

import statistics

from torchsfm.camera import pixels_to_normalized
from torchsfm.geometry.essential import POSE_CANDIDATES, essential_from_fundamental, select_pose
from torchsfm.geometry.fundamental import eight_point
from torchsfm.testing import rotation_error_deg, synthetic_two_view, translation_direction_error_deg

NOISE_LEVELS = [0.0, 0.5, 1.0, 2.0, 4.0]


def main() -> None:
    for rank2 in (True, False):
        print(f"\nE from the {'rank-2' if rank2 else 'raw linear (rank-3)'} 8-point F: median errors in degrees")
        table(rank2)


def table(rank2: bool) -> None:
    print(f"{'noise px':>8s} " + " ".join(f"{method + ' R°':>14s} {method + ' t°':>14s}" for method in POSE_CANDIDATES))
    for noise in NOISE_LEVELS:
        errors = {method: ([], []) for method in POSE_CANDIDATES}
        for seed in range(20):
            scene = synthetic_two_view(200, noise=noise, seed=seed)
            F = eight_point(scene.x1, scene.x2, enforce_rank2_constraint=rank2)
            E = essential_from_fundamental(F, scene.K1, scene.K2)
            n1, n2 = pixels_to_normalized(scene.x1, scene.K1), pixels_to_normalized(scene.x2, scene.K2)
            for method, candidates in POSE_CANDIDATES.items():
                R, t, _ = select_pose(*candidates(E), n1, n2)
                errors[method][0].append(rotation_error_deg(R, scene.R))
                errors[method][1].append(translation_direction_error_deg(t, scene.t))
        cells = [f"{statistics.median(r):14.4f} {statistics.median(t):14.4f}" for r, t in errors.values()]
        print(f"{noise:8.2f} " + " ".join(cells))


if __name__ == "__main__":
    main()
