"""Typed, validated configuration.

Every tunable lives in a frozen dataclass whose defaults are the thesis' values (or, where the
thesis is silent, ours, marked so). ``configs/default.yaml`` spells out the same defaults; a test
keeps the two equal. YAML files and ``key=value`` overrides load strictly: an unknown key, a
value of the wrong type or a name outside a setting's choices (a ``Literal`` type below: the one
list of them) is a :class:`~torchsfm.errors.ConfigError` naming the full key.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
from pathlib import Path
from functools import cache
from typing import Any, Literal, get_args, get_origin, get_type_hints

import yaml

from torchsfm.errors import ConfigError


# The choices of the settings that name a method: each is the single list of its names. The
# registries that map a name to its implementation (``robust.samplers.SAMPLERS``,
# ``robust.ransac.SCORINGS``, ``geometry.triangulation.TRIANGULATION_METHODS``,
# ``geometry.essential.POSE_CANDIDATES``, ``moving.hypotheses.MODELS``) are checked against them
# by a test; the other settings branch on their names where they are used.
Sampler = Literal["bucketed", "uniform"]
Scoring = Literal["inlier_count", "msac"]
Damping = Literal["identity", "diagonal"]
MinimalSolver = Literal["eight_point", "seven_point"]
TriangulationMethod = Literal["midpoint", "linear_eigen", "linear_ls", "iterative_eigen", "iterative_ls", "polynomial"]
PoseMethod = Literal["svd", "linear", "quaternion"]
PoseSolver = Literal["fundamental", "five_point"]
Strength = Literal["sm", "ncc"]
Relaxation = Literal["some_winners", "winner_take_all"]
ResectionSolver = Literal["p3p", "dlt"]
Loss = Literal["none", "huber", "cauchy"]
LinearSolver = Literal["auto", "dense", "cg"]
PairMode = Literal["auto", "sequential", "exhaustive", "similarity"]
Matcher = Literal["ncc", "sift"]
PlaneModel = Literal["quadratic", "homography"]
Selection = Literal["threshold", "rank"]
TrackMethod = Literal["triplets", "rigid_groups", "both", "segmentation"]
MotionModel = Literal["fundamental", "affine", "homography"]


def _require(condition: bool, key: str, value: Any, rule: str) -> None:
    if not condition:
        raise ConfigError(f"config {key}={value!r} is invalid: {rule}")


@cache
def _choices(cls: type) -> dict[str, tuple[str, ...]]:
    """The fields of a config dataclass typed as a ``Literal`` of names, with their choices."""
    return {name: get_args(hint) for name, hint in get_type_hints(cls).items() if get_origin(hint) is Literal}


def _require_choices(section: Any) -> None:
    """Every named-choice field of ``section`` holds one of its choices."""
    for name, choices in _choices(type(section)).items():
        value = getattr(section, name)
        _require(value in choices, name, value, f"one of {', '.join(choices)}")


@dataclass(frozen=True)
class RansacConfig:
    """Settings of the one RANSAC engine (thesis §3.3.3).

    ``inlier_threshold`` is in the residual's own unit: pixels of Sampson distance for the
    fundamental matrix. ``confidence`` is p of eq. 3.3.7. ``hypotheses_per_round`` is how many
    minimal samples are drawn and scored as one batch before the adaptive stop is re-checked.
    Up to ``local_refits`` non-minimal fits on the inliers polish each minimal model that scores
    higher than every one before it (LO-RANSAC; ours, 0 is the thesis' plain RANSAC).
    ``preemptive_points`` > 0 scores every hypothesis on that many random points first and fully
    scores only the best ``preemptive_keep`` fraction (ours, for speed; 0 scores everything on
    all points). ``min_inliers`` > 0 is the support
    below which a model is of no use to the caller (e.g. a resection the mapper would refuse):
    the adaptive count of eq. 3.3.7 takes the inlier ratio as at least ``min_inliers`` / N, so a
    problem stops once it has drawn the samples that find such a model at ``confidence``, even if
    its best has fewer (as COLMAP's ``min_inlier_ratio``; a problem with no such model otherwise
    draws up to ``max_trials``).
    """

    inlier_threshold: float = 1.0
    confidence: float = 0.99
    max_trials: int = 10_000
    hypotheses_per_round: int = 512
    initial_hypotheses: int = 32
    sampler: Sampler = "bucketed"
    grid_size: int = 8
    scoring: Scoring = "inlier_count"
    local_refits: int = 3
    preemptive_points: int = 100
    preemptive_keep: float = 0.125
    min_inliers: int = 0

    def __post_init__(self) -> None:
        _require_choices(self)
        _require(self.inlier_threshold > 0, "inlier_threshold", self.inlier_threshold, "must be > 0")
        _require(0 < self.confidence < 1, "confidence", self.confidence, "must lie in (0, 1)")
        _require(self.max_trials >= 1, "max_trials", self.max_trials, "must be >= 1")
        _require(self.hypotheses_per_round >= 1, "hypotheses_per_round", self.hypotheses_per_round, "must be >= 1")
        _require(self.initial_hypotheses >= 1, "initial_hypotheses", self.initial_hypotheses, "must be >= 1")
        _require(self.grid_size >= 1, "grid_size", self.grid_size, "must be >= 1")
        _require(self.local_refits >= 0, "local_refits", self.local_refits, "must be >= 0")
        _require(self.preemptive_points >= 0, "preemptive_points", self.preemptive_points, "must be >= 0")
        _require(0 < self.preemptive_keep <= 1, "preemptive_keep", self.preemptive_keep, "must lie in (0, 1]")
        _require(self.min_inliers >= 0, "min_inliers", self.min_inliers, "must be >= 0")


@dataclass(frozen=True)
class LMConfig:
    """Levenberg–Marquardt settings (Appendix C; Nielsen's damping update).

    ``initial_damping`` is tau (mu0 = tau * max diag(JᵀJ)); the thesis gives no value, and we
    take Lourakis' recommendation for a start close to the optimum (1e-6; 1e-3 is his choice for
    distant starts), since every torchsfm caller starts LM from a linear estimate — with 1e-3 the
    F refinement needs 9 iterations instead of 3 for the same cost. The three tolerances are
    epsilon_1 (gradient infinity norm), epsilon_2 (step relative to the parameters) and a relative
    cost decrease below which the iteration stops (ours; 1e-6, Ceres' default function tolerance:
    for m residuals of noise σ the cost is about m σ² / 2, so such a step lowers it by under
    5e-7·m σ² and moves the estimate by a small fraction of its standard deviation, about 0.1
    for m = 10⁴ — below the noise, and a batch's last iterations no longer wait on it).
    ``damping`` is ``identity`` (mu I, the thesis) or ``diagonal`` (mu diag(JᵀJ), Marquardt's
    scale-invariant choice; then mu0 = tau).
    """

    max_iterations: int = 100
    initial_damping: float = 1e-6
    damping: Damping = "identity"
    gradient_tolerance: float = 1e-10
    step_tolerance: float = 1e-10
    cost_tolerance: float = 1e-6

    def __post_init__(self) -> None:
        _require_choices(self)
        _require(self.max_iterations >= 1, "max_iterations", self.max_iterations, "must be >= 1")
        for name in ("initial_damping", "gradient_tolerance", "step_tolerance", "cost_tolerance"):
            value = getattr(self, name)
            _require(value > 0 and math.isfinite(value), name, value, "must be a finite number > 0")


@dataclass(frozen=True)
class FundamentalConfig:
    """Robust F (§3.3): RANSAC on the normalized 8-point algorithm, then LM on the Sampson error.

    With ``refine``, ``refine_rounds`` LM runs each minimize the Sampson error over the points
    within ``refine_support_factor`` × the inlier threshold of the current F (ours: a support
    wider than the threshold keeps the noise distribution untruncated, which measurably lowers
    the error of F; the returned inlier mask still uses the threshold itself). ``minimal_solver``
    ``seven_point`` samples 7 correspondences (up to three F each) instead of 8. The RANSAC's LO
    refits (``ransac.local_refits``, 20 here) of a record minimal model go on while its inliers
    move: from a minimal sample of noisy points that takes 3-8 refits at 30 % outliers and up to
    31 at 60-70 % (20 bound all but 2 of the 211 measured), and a model stopped after 3 kept a
    worse F. Measured on 30 synthetic scenes of 1000 matches, 0.5 px noise, per outlier share,
    the median epipolar error of the true matches: at worst 0.085 px at 30 %, 0.185 px at 50 %;
    at 60 % 0.120 px at the 90th percentile and 0.462 px at worst (OpenCV USAC_MAGSAC: 0.097,
    0.126, 0.142 and 0.155 px).
    """

    ransac: RansacConfig = field(default_factory=lambda: RansacConfig(local_refits=20))
    refine: bool = True
    refine_rounds: int = 1
    refine_support_factor: float = 1.5
    minimal_solver: MinimalSolver = "eight_point"

    def __post_init__(self) -> None:
        _require_choices(self)
        _require(self.refine_rounds >= 1, "refine_rounds", self.refine_rounds, "must be >= 1")
        _require(self.refine_support_factor >= 1, "refine_support_factor", self.refine_support_factor, "must be >= 1")


@dataclass(frozen=True)
class TriangulationConfig:
    """Triangulation (§3.5). ``method`` is one of :data:`torchsfm.geometry.TRIANGULATION_METHODS`.

    The iterative methods (Hartley & Sturm) stop after ``max_iterations`` reweightings or when the
    weights change by less than ``tolerance`` (relative).
    """

    method: TriangulationMethod = "polynomial"
    max_iterations: int = 10
    tolerance: float = 1e-10

    def __post_init__(self) -> None:
        _require_choices(self)
        _require(self.max_iterations >= 1, "max_iterations", self.max_iterations, "must be >= 1")
        _require(self.tolerance > 0, "tolerance", self.tolerance, "must be > 0")


@dataclass(frozen=True)
class RelativePoseConfig:
    """Calibrated relative pose (§3.4): E = K2ᵀ F K1 → (R, t̂).

    ``method`` decomposes E: ``svd`` (default), ``linear`` (eq. 3.4.10–3.4.11) or
    ``quaternion`` (eq. 3.4.12–3.4.15), each followed by the cheirality test. With ``refine``
    (ours; the thesis stops at the decomposition) the pose is refined by LM on the Sampson error
    from ``num_starts`` + 1 starts (see :mod:`torchsfm.estimators.calibrated_pose`; extra starts are
    fitted to random subsets of ``start_sample_size`` of F's inliers; the ``kept_starts`` best go
    on after the first stage), re-classifying its support
    with thresholds shrinking from ``start_threshold_factor`` to ``refine_support_factor`` times
    the inlier threshold (``fundamental.ransac.inlier_threshold``).

    ``solver`` is what RANSAC fits: ``fundamental`` (the thesis: F by ``fundamental``, then E =
    K2ᵀ F K1) or ``five_point`` (ours: E directly by the five-point algorithm of Stewénius et
    al. 2006, up to ten E per sample of five; far fewer samples for the same confidence — at 60 %
    outliers about 700 instead of the 10 000 cap — and no F refinement). The LM then starts from
    E and the ``num_starts`` extra starts as above; from E alone (``num_starts = 0``) it is about
    2× faster and as accurate on ``benchmarks/two_view.py``'s scenes, but from one start it can
    settle on a wrong optimum: at 60 % outliers, one of ten synthetic scenes with RANSAC seed 0
    (1.7° in t, against 0.2° with the extra starts).

    A pose whose inliers show no parallax beyond noise has no determined translation: the
    camera turned in place or did not move. It is an error, not a pose (the sign test of
    :func:`~torchsfm.geometry.essential.parallax_is_noise` at ``parallax_significance``, with
    the inlier threshold as 2σ of the Sampson distance: the median inlier within the noise, and
    no excess beyond it on the front side of infinity, where points in front of both cameras
    lie, over the other, where mismatches along the epipolar lines fall as often).
    """

    method: PoseMethod = "svd"
    solver: PoseSolver = "fundamental"
    refine: bool = True
    num_starts: int = 16
    kept_starts: int = 4
    start_sample_size: int = 16
    start_threshold_factor: float = 4.0
    refine_support_factor: float = 1.5
    parallax_significance: float = 1e-3

    def __post_init__(self) -> None:
        _require_choices(self)
        _require(self.num_starts >= 0, "num_starts", self.num_starts, "must be >= 0")
        _require(0 < self.parallax_significance < 1, "parallax_significance", self.parallax_significance, "must lie in (0, 1)")
        _require(self.kept_starts >= 1, "kept_starts", self.kept_starts, "must be >= 1")
        _require(self.start_sample_size >= 8, "start_sample_size", self.start_sample_size, "must be >= 8")
        _require(self.refine_support_factor >= 1, "refine_support_factor", self.refine_support_factor, "must be >= 1")
        _require(self.start_threshold_factor >= self.refine_support_factor, "start_threshold_factor",
                 self.start_threshold_factor, "must be >= refine_support_factor")


@dataclass(frozen=True)
class HarrisConfig:
    """Harris corners (§3.2.1, Alg. 3.2.1, Appendix B).

    ``k`` = 0.04 (thesis, after Harris). ``window`` is N of the N×N Gaussian on the gradient
    products, of the non-maximum suppression and of the biquadric support (thesis: the same N
    for all three; N = 3). A corner needs R > ``relative_threshold`` × the image's largest R.
    At most ``max_corners`` are kept; with ``spread_grid`` G > 0 each of G×G cells first keeps
    its best ceil(max_corners / G²) so that corners cover the image. ``subpixel`` switches the
    biquadric fit (False: pixel accuracy, for comparison). Corners closer than ``border``
    pixels to the image edge are dropped (the NCC patches need room). Thresholds and counts are
    ours: the thesis gives none.
    """

    k: float = 0.04
    window: int = 3
    relative_threshold: float = 1e-4
    max_corners: int = 2000
    spread_grid: int = 8
    subpixel: bool = True
    border: int = 8

    def __post_init__(self) -> None:
        _require(self.window >= 3 and self.window % 2 == 1, "window", self.window, "must be an odd number >= 3")
        _require(0 <= self.relative_threshold < 1, "relative_threshold", self.relative_threshold, "must lie in [0, 1)")
        _require(self.max_corners >= 8, "max_corners", self.max_corners, "must be >= 8")
        _require(self.spread_grid >= 0, "spread_grid", self.spread_grid, "must be >= 0")
        _require(self.border >= 0, "border", self.border, "must be >= 0")


@dataclass(frozen=True)
class MatchingConfig:
    """Putative matches (§3.2.2): NCC candidates, strength measure, relaxation.

    NCC on (2 ``patch_half_size`` + 1)² patches between corners less than ``search_radius``
    pixels apart, kept above ``ncc_threshold``. ``strength``: ``sm`` ranks candidates by the
    strength measure (neighbours within ``neighbourhood_radius``, relative distance threshold
    ``relative_distance_threshold`` = ε_r); ``ncc`` by the correlation alone (the thesis'
    baseline). ``relaxation``: ``some_winners`` (thesis default, top ``alpha`` of both tables)
    or ``winner_take_all``; it stops when no candidate above ``strength_threshold`` is left or
    after ``max_relaxation_iterations``. Values follow Zhang et al. (1995) where the thesis gives
    none (ε_r = 0.3, NCC > 0.8).

    ``reference_size``: the image size, √(H W) in pixels, the two radii are for: the pipelines
    (:meth:`for_images`) shrink them for smaller images, 0 never (:func:`match_corners` itself
    takes them as given).
    """

    patch_half_size: int = 5
    search_radius: float = 100.0
    ncc_threshold: float = 0.8
    strength: Strength = "sm"
    neighbourhood_radius: float = 80.0
    relative_distance_threshold: float = 0.3
    relaxation: Relaxation = "some_winners"
    alpha: float = 0.6
    strength_threshold: float = 0.0
    max_relaxation_iterations: int = 100
    reference_size: float = 627.0

    def __post_init__(self) -> None:
        _require_choices(self)
        _require(self.patch_half_size >= 1, "patch_half_size", self.patch_half_size, "must be >= 1")
        _require(self.reference_size >= 0, "reference_size", self.reference_size, "must be >= 0")
        _require(self.search_radius > 0, "search_radius", self.search_radius, "must be > 0")
        _require(-1 <= self.ncc_threshold < 1, "ncc_threshold", self.ncc_threshold, "must lie in [-1, 1)")
        _require(self.neighbourhood_radius > 0, "neighbourhood_radius", self.neighbourhood_radius, "must be > 0")
        _require(0 < self.relative_distance_threshold <= 2, "relative_distance_threshold", self.relative_distance_threshold,
                 "must lie in (0, 2] (the relative difference of two distances never exceeds 2)")
        _require(0 < self.alpha <= 1, "alpha", self.alpha, "must lie in (0, 1]")
        _require(self.max_relaxation_iterations >= 1, "max_relaxation_iterations", self.max_relaxation_iterations, "must be >= 1")

    def for_images(self, *shapes: tuple[int, ...]) -> MatchingConfig:
        """These settings for matching a set of images of ``shapes`` (..., H, W): ``search_radius``
        and ``neighbourhood_radius`` times √(H W) / ``reference_size`` of its largest image where
        that is below 1 (a set from several cameras is matched at its largest image's scale, as
        its coarse matching is). The corner budget (``harris.max_corners``) is fixed, so a disc of
        a fixed radius in a smaller image holds more of its corners — at half the size four times
        the candidates and strength-measure neighbours: slower, and more chance candidates for the
        relaxation — and the scene moves across fewer pixels. Larger images keep the radii: the
        coarse homography centres their discs, and growing them cost time without a measured gain
        (Herz-Jesu-P8 at twice the size)."""
        scale = max(math.sqrt(shape[-2] * shape[-1]) for shape in shapes) / self.reference_size if self.reference_size else 1.0
        if scale >= 1:
            return self
        return dataclasses.replace(self, search_radius=self.search_radius * scale, neighbourhood_radius=self.neighbourhood_radius * scale)


@dataclass(frozen=True)
class ResectionConfig:
    """Camera resection (§4.1–4.2): RANSAC with reprojection error (pixels; default threshold
    2 px, ours), minimal ``solver`` ``p3p`` (calibrated, 3 pairs; default, chosen by
    benchmarks/resection.py) or ``dlt`` (thesis, 6 pairs), then LM on the pose (``refine``) over
    the pairs within ``refine_support_factor`` × the threshold. RANSAC polishes each new best
    pose with one LO refit: the LM refines the pose anyway, but the refit raises the inlier
    count the adaptive stop reads, and the LM's support comes from a better pose. Without it
    (benchmarks/resection.py, 10 scenes) P3P runs 7 % faster with the same errors, but the
    6-point DLT needs 2.2× the time and loses accuracy (rotation 0.0152 → 0.0165°)."""

    ransac: RansacConfig = field(default_factory=lambda: RansacConfig(inlier_threshold=2.0, local_refits=1))
    solver: ResectionSolver = "p3p"
    refine: bool = True
    refine_support_factor: float = 1.5

    def __post_init__(self) -> None:
        _require_choices(self)
        _require(self.refine_support_factor >= 1, "refine_support_factor", self.refine_support_factor, "must be >= 1")


def _bundle_lm() -> LMConfig:
    return LMConfig(max_iterations=100, initial_damping=1e-4, damping="diagonal",
                    gradient_tolerance=1e-10, step_tolerance=1e-10, cost_tolerance=1e-6)


@dataclass(frozen=True)
class BundleAdjustmentConfig:
    """Sparse bundle adjustment (Appendix D). ``lm`` holds its own LM settings (Marquardt's
    diagonal damping by default: camera and point parameters have unlike units; the cost
    tolerance 1e-6 is Ceres' default function tolerance). ``loss``:
    ``none``, ``huber`` or ``cauchy`` with ``loss_scale`` pixels. ``linear_solver``: ``dense``
    (Cholesky of the reduced camera system), ``cg`` (preconditioned conjugate gradients) or
    ``auto`` (dense up to ``dense_limit`` camera parameters: 500 views of 6 parameters, a 72 MB
    matrix; measured on a 500-frame video, dense Cholesky adjusts in 72 s where CG, whose
    iterations grow with the length of a chain of views, took 771 s; beyond it CG keeps the memory
    linear in the views). CG stops at a relative residual of ``cg_tolerance`` or after
    ``cg_max_iterations``."""

    lm: LMConfig = field(default_factory=_bundle_lm)
    loss: Loss = "none"
    loss_scale: float = 1.0
    linear_solver: LinearSolver = "auto"
    dense_limit: int = 3000
    cg_tolerance: float = 1e-6
    cg_max_iterations: int = 500

    def __post_init__(self) -> None:
        _require_choices(self)
        _require(self.loss_scale > 0, "loss_scale", self.loss_scale, "must be > 0")
        _require(self.dense_limit >= 1, "dense_limit", self.dense_limit, "must be >= 1")
        _require(self.cg_tolerance > 0, "cg_tolerance", self.cg_tolerance, "must be > 0")
        _require(self.cg_max_iterations >= 1, "cg_max_iterations", self.cg_max_iterations, "must be >= 1")


@dataclass(frozen=True)
class TwoViewConfig:
    """The two-image pipeline (§3.1). Matched corners must move by a median of at least
    ``min_median_parallax`` pixels, else the images are reported as having no baseline."""

    min_median_parallax: float = 1.0

    def __post_init__(self) -> None:
        _require(self.min_median_parallax >= 0, "min_median_parallax", self.min_median_parallax, "must be >= 0")


@dataclass(frozen=True)
class PairsConfig:
    """Which view pairs are matched, and the coarse matching that guides them
    (:mod:`torchsfm.sfm.pairs`).

    ``mode``: ``sequential`` (pairs (i, i + d), d = 1 .. ``window``: video), ``exhaustive``,
    ``similarity`` (each view's ``neighbours`` best partners by the coarse score and the pairs of
    the sequential window, those with ``min_score`` coarse matches and as many inliers of a
    coarse homography; a view left with none keeps its best partners), or ``auto`` (similarity,
    over every pair up to ``exhaustive_up_to`` views). ``second_links`` (those two modes): a
    chosen pair that alone joins two parts of the chosen pairs' graph gets a second pair across
    the same cut, the considered one with the most coarse homography inliers
    (:func:`torchsfm.sfm.pairs.second_links`). Coarse matching: images reduced to about
    ``coarse_size`` px on the long side, ``coarse_corners`` Harris corners, NCC on
    (2 ``patch_half_size`` + 1)² patches, mutual best above ``ncc_threshold``. ``guided``: a
    homography fitted to the coarse matches (``homography_threshold`` px, at least ``min_score``
    inliers) centres the full-resolution search disc of every corner on its predicted position;
    with ``warp_patches``, each corner's NCC patch is also warped by the homography's local
    affine map, so rotation, scale and foreshortening between the views are undone.
    ``epipolar_matching``: when views stay unregistered, their verified pairs are matched again
    with the epipolar band (Sampson distance within the F inlier threshold) in place of the disc,
    and the mapping runs again. ``sift_bridge``: when views are still left out, the pairs that
    may link them to the model take their homography from the coarse NCC matches with one view's
    patches turned every 30 degrees (portrait and landscape shots, tilted ones), or else from SIFT matches
    (wide baselines), are matched and verified as above, and the mapping runs again.
    ``matcher``: ``ncc`` (the thesis' Harris corners and NCC + strength measure, above) or
    ``sift`` (Kornia's SIFT: ``sift_features`` scale-space keypoints per view, RootSIFT
    descriptors, mutual nearest neighbours passing Lowe's ratio test at ``sift_ratio``; the same
    pair selection, verification and mapper).
    """

    mode: PairMode = "auto"
    window: int = 2
    exhaustive_up_to: int = 8
    neighbours: int = 4
    min_score: int = 12
    second_links: bool = True
    coarse_size: int = 320
    coarse_corners: int = 300
    patch_half_size: int = 4
    ncc_threshold: float = 0.8
    homography_threshold: float = 8.0
    guided: bool = True
    warp_patches: bool = True
    epipolar_matching: bool = True
    sift_bridge: bool = True
    matcher: Matcher = "ncc"
    sift_features: int = 4000
    sift_ratio: float = 0.8

    def __post_init__(self) -> None:
        _require_choices(self)
        _require(self.sift_features >= 8, "sift_features", self.sift_features, "must be >= 8")
        _require(0 < self.sift_ratio <= 1, "sift_ratio", self.sift_ratio, "must lie in (0, 1]")
        _require(self.window >= 1, "window", self.window, "must be >= 1")
        _require(self.exhaustive_up_to >= 2, "exhaustive_up_to", self.exhaustive_up_to, "must be >= 2")
        _require(self.neighbours >= 0, "neighbours", self.neighbours, "must be >= 0")
        _require(self.min_score >= 4, "min_score", self.min_score, "must be >= 4")
        _require(self.coarse_size >= 64, "coarse_size", self.coarse_size, "must be >= 64")
        _require(self.coarse_corners >= 8, "coarse_corners", self.coarse_corners, "must be >= 8")
        _require(self.patch_half_size >= 1, "patch_half_size", self.patch_half_size, "must be >= 1")
        _require(-1 <= self.ncc_threshold < 1, "ncc_threshold", self.ncc_threshold, "must lie in [-1, 1)")
        _require(self.homography_threshold > 0, "homography_threshold", self.homography_threshold, "must be > 0")


@dataclass(frozen=True)
class ReconstructionConfig:
    """Incremental reconstruction of a sequence (thesis chapter 4).

    The view pairs chosen by ``pairs`` are matched; a pair's matches are kept if the robust F
    keeps at least ``min_pair_inliers``. The initial pair is the one with
    most inliers among those whose homography explains at most ``max_homography_ratio`` of the F
    inliers (``homography_threshold`` px) and whose inliers triangulate with a median angle of at
    least ``min_initial_angle`` degrees (where no pair, matched or linked through tracks, reaches
    it: half of it, as COLMAP relaxes its initial angle). Each next view is resected from its tracks' 3-D points
    and needs ``min_resection_inliers`` (the resection threshold doubles, up to
    ``max_resection_threshold`` px, while it keeps fewer: see :func:`torchsfm.sfm.mapping.resect`); with
    ``track_against_map``, a view that needs a widened threshold, or keeps too few even at the
    widest, is tracked against the map: the model's points searched (NCC) within the widest
    threshold of where that resection puts them, and the view resected again at the RANSAC
    threshold from what is found (:func:`torchsfm.sfm.mapping.pose_by_tracking`). New points need a triangulation angle of
    ``min_point_angle`` degrees, reprojection errors below ``max_reprojection_error`` px and
    ``min_track_views`` views at the end (the thesis keeps points seen in ≥ 3 views: set 3).
    Images whose larger side exceeds ``max_image_size`` px (0: never) are reduced by the smallest
    integer factor that brings them within it (block averages) before any detection: the
    detector's and matcher's pixel settings (11-pixel patches, the search disc, the
    strength-measure neighbourhood) describe image structure at about a thousand pixels across,
    and a 12-megapixel photo's corners at full resolution are fine texture (COLMAP bounds its
    SIFT input likewise, ``max_image_size``); the model is reported at the input resolution.
    Bundle adjustment runs every ``bundle_every`` new views (0: only at the end) and at the end;
    with ``local_bundle_window`` W > 0, each new view that no full adjustment follows gets a local
    adjustment of the W newest views and the points they see (the older views that see those points hold
    them fixed), so a long sequence's poses stay adjusted at a cost bounded by W, not by its length.
    With ``keyframes``, a frame whose camera did not move from the last keyframe before it (its
    tracks moved less than half a pixel, median: a car waiting at a light) stays out of all of this
    and is resected from the finished model (:func:`torchsfm.sfm.mapping.still_frames`).
    Then, ``retriangulations`` times, the tracks without a point are triangulated again from the
    adjusted cameras and the model adjusted once more; then once with every observation within twice
    ``max_reprojection_error`` (those the gate dropped against earlier cameras, which the later
    adjustments fitted their points without), before the gate drops outliers for the last
    adjustment. The pipeline's adjustments use the robust
    ``bundle_loss`` (at ``bundle_adjustment.loss_scale`` px): real matches hold outliers that
    survive the epipolar and reprojection tests (``bundle_adjustment.loss`` stays the plain least
    squares of :func:`torchsfm.bundle_adjust`). Without K, the last adjustments also refine the
    ``refined_intrinsics`` of the K all views share (comma-separated: ``f`` for one square-pixel
    focal length or ``fx``, ``fy``, and ``cx``, ``cy``, and ``k1``: one radial distortion
    coefficient, the model's cameras then carrying it and its keypoints as detected), each kept
    only where the data determine it; alternatives separated by ``|`` are each refined from the
    same start and the one with the smallest geometric AIC kept (default: a free principal point,
    or one radial coefficient with the principal point at the image centre;
    :func:`torchsfm.sfm.mapping.refine_intrinsics`). Last, with ``observations_by_projection``,
    every registered view is searched around the projections of the points it does not observe
    but its verified partners do (the NCC of a partner's patch warped to it;
    :mod:`torchsfm.sfm.projection_search`), what is found joins the tracks, and the model is
    adjusted once more.
    """

    min_pair_inliers: int = 30
    homography_threshold: float = 3.0
    max_homography_ratio: float = 0.8
    min_initial_angle: float = 2.0
    min_resection_inliers: int = 20
    max_resection_threshold: float = 8.0
    track_against_map: bool = True
    max_image_size: int = 1600
    min_point_angle: float = 1.0
    max_reprojection_error: float = 2.0
    min_track_views: int = 2
    bundle_every: int = 0
    local_bundle_window: int = 0
    keyframes: bool = True
    retriangulations: int = 1
    observations_by_projection: bool = True
    bundle_loss: Loss = "cauchy"
    refined_intrinsics: str = "f,cx,cy|f,k1"

    def __post_init__(self) -> None:
        _require_choices(self)
        for alternative in self.refined_intrinsics.split("|"):
            names = [name for name in alternative.split(",") if name]
            _require(all(name in ("f", "fx", "fy", "cx", "cy", "k1") for name in names) and len(set(names)) == len(names)
                     and not ("f" in names and {"fx", "fy"} & set(names)), "refined_intrinsics", self.refined_intrinsics,
                     "distinct names of f (or fx, fy), cx, cy, k1, comma-separated; alternatives separated by |")
        _require(self.retriangulations >= 0, "retriangulations", self.retriangulations, "must be >= 0")
        _require(self.min_pair_inliers >= 8, "min_pair_inliers", self.min_pair_inliers, "must be >= 8")
        _require(self.homography_threshold > 0, "homography_threshold", self.homography_threshold, "must be > 0")
        _require(0 < self.max_homography_ratio <= 1, "max_homography_ratio", self.max_homography_ratio, "must lie in (0, 1]")
        _require(self.min_initial_angle >= 0, "min_initial_angle", self.min_initial_angle, "must be >= 0")
        _require(self.min_resection_inliers >= 6, "min_resection_inliers", self.min_resection_inliers, "must be >= 6")
        _require(self.max_image_size >= 0, "max_image_size", self.max_image_size, "must be >= 0")
        _require(self.max_resection_threshold > 0, "max_resection_threshold", self.max_resection_threshold, "must be > 0")
        _require(self.min_point_angle >= 0, "min_point_angle", self.min_point_angle, "must be >= 0")
        _require(self.max_reprojection_error > 0, "max_reprojection_error", self.max_reprojection_error, "must be > 0")
        _require(self.min_track_views >= 2, "min_track_views", self.min_track_views, "must be >= 2")
        _require(self.bundle_every >= 0, "bundle_every", self.bundle_every, "must be >= 0")
        _require(self.local_bundle_window >= 0, "local_bundle_window", self.local_bundle_window, "must be >= 0")


@dataclass(frozen=True)
class MovingObjectsConfig:
    """Rejection of independently moving objects (thesis chapter 5, Alg. 5.4.1).

    Frames 0 and 2 are registered to frame 1 (the reference) by the dominant plane:
    ``plane_model`` ``quadratic`` (eq. 5.2.1) or ``homography`` (exact for finite motions), found
    by RANSAC (``plane_ransac``; threshold in pixels) and refitted on its inliers; the plane must
    explain at least ``min_plane_share`` of the vectors. Rigidity residuals (eq. 5.3.2) are
    normalized to pixels by first-order noise propagation, so ``rigidity_threshold`` (t1) is a
    pixel noise level and holds across image sizes. ``neighbourhood`` (d1) is a fraction of the
    diagonal of the reference points' bounding box (the thesis' 60 px on its 640×480 images is
    0.075). Seeds and supports need a residual parallax of at least ``min_support_parallax`` px
    (smaller ones carry no information). ``seed_candidates`` (N), ``supports`` (M),
    ``keep_fraction`` (p) and ``min_votes`` (K) are the thesis' parameters; ``selection``
    ``rank`` keeps the best p of every support's residuals (thesis), ``threshold`` keeps those
    within t1 (ours: p caps the background at a share p of the vectors). A static scene's
    parallax grows from zero at the plane, a moving object's is offset as a whole: when the plane
    explains at least ``planar_background_share`` of the vectors and the 10th percentile of the
    parallax norms of IMOR's background is above ``planar_background_ratio`` times their median,
    that rigid group is taken for an object on a planar background (Irani & Anandan's 2D case)
    and every vector with parallax is rejected (ours; a heuristic prior: with three frames or
    more, a rigid object over a planar background is geometrically as valid a static scene). With ``ransac`` the
    IMOR background goes on to RANSAC on the fundamental matrices of frame pairs (1, 0), (1, 2)
    and (0, 2) (IMOR + RANSAC), with ``fundamental``'s settings except a first round of
    ``ransac_initial_hypotheses`` samples (IMOR's background is nearly clean: a few samples
    usually meet the adaptive stop). Over longer tracks, every frame triplet votes and a vector
    rejected by at least ``min_rejection_share`` of the triplets that tested it is rejected
    (ours). Whole tracks (:func:`torchsfm.reject_moving_objects_in_tracks`, gaps allowed) are
    judged by ``track_method``: ``segmentation`` (default: every rigid motion segmented by
    :func:`torchsfm.segment_motions` with the ``segmentation`` settings, its static scene kept;
    measured on Hopkins155 and KT3DMoSeg the most accurate), ``triplets`` (those votes), ``rigid_groups`` (up to
    ``max_motions`` rigid groups of at least ``min_group_tracks`` tracks, each a projective
    reconstruction over all frames whose cameras come from ``resection_ransac`` and at most
    ``track_refinements`` alternations, fewer once they converge; a track belongs to a group
    within the larger of the χ² bound at ``track_significance`` and ``track_tolerance`` px RMS;
    the static group is the one the votes reject least) or ``both``. ``enabled`` turns the
    rejection on in the two-view and multi-view pipelines. With ``reconstruct_objects`` pair
    verification also keeps a second motion's matches (a second F on the first one's outliers,
    at least ``min_object_tracks``), which one F per pair would throw away, and the multi-view
    pipeline segments the tracks (``track_method`` ``segmentation`` whatever it is set to),
    reconstructs the static scene from label 0 and each moving body with at least
    ``min_object_tracks`` tracks seen in at least ``min_object_frames`` frames as its own model
    (:class:`~torchsfm.reconstruction.MovingObject`).
    A body is reconstructed ``object_starts`` times from independent random draws and the model
    that registers most frames, then has the smallest truncated squared reprojection error, is
    kept (:func:`~torchsfm.sfm.from_tracks.reconstruct_body`): a small body's two-view geometry can be ill-conditioned, and the initial pair with
    most inliers may carry a pose far off that bundle adjustment cannot leave (measured on the
    synthetic boxes of ``examples/moving_bodies.py``: 10-12 deg from one start where bundle
    adjustment from the truth reaches 0.2-1.3 deg).
    """

    plane_model: PlaneModel = "homography"
    plane_ransac: RansacConfig = field(default_factory=lambda: RansacConfig(inlier_threshold=2.0, max_trials=2000, initial_hypotheses=128, local_refits=1))
    min_plane_share: float = 0.1
    seed_candidates: int = 20
    rigidity_threshold: float = 1.0
    neighbourhood: float = 0.075
    min_support_parallax: float = 2.0
    supports: int = 10
    keep_fraction: float = 0.7
    min_votes: int = 6
    selection: Selection = "threshold"
    planar_background_ratio: float = 0.55
    planar_background_share: float = 0.4
    ransac: bool = True
    ransac_initial_hypotheses: int = 4
    min_rejection_share: float = 0.25
    track_method: TrackMethod = "segmentation"
    max_motions: int = 5
    min_group_tracks: int = 8
    track_tolerance: float = 1.0
    track_significance: float = 1e-3
    track_refinements: int = 3
    resection_ransac: RansacConfig = field(default_factory=lambda: RansacConfig(inlier_threshold=2.0, max_trials=2000))
    enabled: bool = False
    reconstruct_objects: bool = False
    min_object_tracks: int = 20
    min_object_frames: int = 3
    object_starts: int = 3

    def __post_init__(self) -> None:
        _require_choices(self)
        _require(self.object_starts >= 1, "object_starts", self.object_starts, "must be >= 1")
        _require(self.min_object_tracks >= 8, "min_object_tracks", self.min_object_tracks, "must be >= 8")
        _require(self.min_object_frames >= 2, "min_object_frames", self.min_object_frames, "must be >= 2")
        _require(0 < self.min_plane_share <= 1, "min_plane_share", self.min_plane_share, "must lie in (0, 1]")
        _require(self.seed_candidates >= 1, "seed_candidates", self.seed_candidates, "must be >= 1")
        _require(self.rigidity_threshold > 0, "rigidity_threshold", self.rigidity_threshold, "must be > 0")
        _require(0 <= self.neighbourhood < 1, "neighbourhood", self.neighbourhood, "must lie in [0, 1)")
        _require(self.min_support_parallax >= 0, "min_support_parallax", self.min_support_parallax, "must be >= 0")
        _require(self.supports >= 1, "supports", self.supports, "must be >= 1")
        _require(0 < self.keep_fraction <= 1, "keep_fraction", self.keep_fraction, "must lie in (0, 1]")
        _require(1 <= self.min_votes <= self.supports, "min_votes", self.min_votes, "must lie in [1, supports]")
        _require(self.planar_background_ratio > 0, "planar_background_ratio", self.planar_background_ratio, "must be > 0")
        _require(0 < self.planar_background_share <= 1, "planar_background_share", self.planar_background_share, "must lie in (0, 1]")
        _require(self.ransac_initial_hypotheses >= 1, "ransac_initial_hypotheses", self.ransac_initial_hypotheses, "must be >= 1")
        _require(self.max_motions >= 1, "max_motions", self.max_motions, "must be >= 1")
        _require(self.min_group_tracks >= 6, "min_group_tracks", self.min_group_tracks, "must be >= 6 (a camera needs 6 points)")
        _require(self.track_tolerance > 0, "track_tolerance", self.track_tolerance, "must be > 0")
        _require(0 < self.track_significance < 1, "track_significance", self.track_significance, "must lie in (0, 1)")
        _require(self.track_refinements >= 0, "track_refinements", self.track_refinements, "must be >= 0")
        _require(0 < self.min_rejection_share <= 1, "min_rejection_share", self.min_rejection_share, "must lie in (0, 1]")


@dataclass(frozen=True)
class SegmentationConfig:
    """Motion segmentation by preference clustering (:mod:`torchsfm.moving.segmentation`).

    Each round samples ``hypotheses`` models, shared equally by the kinds in ``models`` that it
    uses (``fundamental``: an 8-point F over every pair of ``sample_frames`` frames; ``affine``:
    the affine-camera trajectory subspace of 4 tracks over ``affine_frames`` frames;
    ``homography``: a plane's 4-point homographies over every pair of ``sample_frames`` frames,
    used on three frames or more only: between two frames a plane's transfer error ranks a
    body's off-plane points with other bodies', and AdelaideRMF's misclassification rose from
    12.0 to 46.9 % with it). Over 10 seeds the three kinds sharing 4000 samples, against F and
    affine at 2000 each (the same cost), lowered the mean misclassification from 5.23 to 4.61 %
    on Hopkins155 and from 13.18 to 10.66 % on KT3DMoSeg (two views: the same two kinds at
    2000 each, unchanged). The first round draws a share
    ``local_share`` of the samples among a seed track's ``neighbours`` nearest tracks; the
    ``guided_rounds`` that follow draw them in proportion to the previous round's similarity. A
    track prefers the ``preference_share`` of its hypotheses with the smallest residuals (ranks:
    no noise threshold); the Tanimoto affinity
    keeps each track's ``links`` strongest links. Tracks whose ``support`` most similar tracks are
    on average at most ``outlier_factor`` times as similar as chance are outliers. Spectral
    k-means cuts the rest into ``pieces`` (``restarts`` batched restarts of
    ``kmeans_iterations``), merged by link strength; the number of motions (static scene
    included, at most ``max_motions``) is the one before the largest drop of the merge links
    (links below ``link_floor`` count as none; one motion if no drop reaches
    ``min_link_drop``). Tracks seen in fewer than ``min_frames`` frames are left unassigned.
    More than ``max_tracks`` tracks (the affinity is N × N): a seeded subset of that many is
    clustered and every other track goes to the motion whose fundamental matrices explain it
    best, within 3× that motion's median residual (else it is left unassigned). The static scene
    becomes what its rigid motion explains (when the number of motions is given: if that leaves
    that many motions, else the pieces are cut into that many as they are):
    other motions it explains join it, pieces of it that it does not explain are cut out as
    moving bodies (or outliers, where no rigid motion explains them within the χ² bound of noise
    at ``scene_tolerance``) — a track is explained within the larger of ``scene_tolerance`` px (the
    tracker's noise floor) and the χ² bound at ``scene_significance``, a motion or piece by the
    majority of its tracks (:func:`torchsfm.moving.scene.settle_scene`); the residual is
    the scene's projective reconstruction (at most ``scene_refinements`` camera / point alternations)
    when the scene has parallax beyond that floor, else one F per frame pair. With ``runs`` > 1
    all of this runs that many times on successive draws of the generator, and the partition that
    agrees most with the others (the largest sum of adjusted Rand indices: the ensemble's medoid,
    Strehl & Ghosh 2002) is the result; ties go to the earliest run. Measured with 3 runs against
    1, over seeds 0-9 (``examples/motion_segmentation.py --set segmentation.runs=3``), mean
    misclassification with the number of motions given: Hopkins155 1.67 → 0.64 %, AdelaideRMF-F
    13.59 → 12.60 %, KT3DMoSeg 6.04 → 7.25 %; found: Hopkins155 4.34 → 4.34 %, KT3DMoSeg 5.85 →
    5.04 %, AdelaideRMF-F 12.57 → 12.19 % — for 3× the time; so 1 by default.
    """

    hypotheses: int = 4000
    models: str = "fundamental,affine,homography"
    sample_frames: int = 3
    affine_frames: int = 5
    local_share: float = 0.5
    neighbours: int = 24
    preference_share: float = 0.1
    links: int = 24
    guided_rounds: int = 2
    max_motions: int = 6
    pieces: int = 20
    link_floor: float = 0.005
    support: int = 8
    outlier_factor: float = 3.0
    min_link_drop: float = 2.0
    restarts: int = 10
    kmeans_iterations: int = 30
    min_frames: int = 3
    max_tracks: int = 3000
    scene_tolerance: float = 1.0
    scene_significance: float = 1e-3
    scene_refinements: int = 10
    runs: int = 1

    @property
    def model_kinds(self) -> list[str]:
        """``models`` as a list."""
        return [kind.strip() for kind in self.models.split(",") if kind.strip()]

    def kinds_for(self, frames: int) -> list[str]:
        """The hypothesis kinds used on ``frames`` frames: ``model_kinds`` without
        ``homography`` on two frames (unless it is the only one)."""
        kinds = [kind for kind in self.model_kinds if frames >= 3 or kind != "homography"]
        return kinds or self.model_kinds

    def __post_init__(self) -> None:
        _require(self.hypotheses >= 10, "hypotheses", self.hypotheses, "must be >= 10")
        _require(self.max_tracks >= 100, "max_tracks", self.max_tracks, "must be >= 100")
        _require(self.scene_tolerance > 0, "scene_tolerance", self.scene_tolerance, "must be > 0")
        _require(self.scene_refinements >= 0, "scene_refinements", self.scene_refinements, "must be >= 0")
        _require(self.runs >= 1, "runs", self.runs, "must be >= 1")
        _require(0 < self.scene_significance < 1, "scene_significance", self.scene_significance, "must lie in (0, 1)")
        _require(bool(self.model_kinds) and set(self.model_kinds) <= set(get_args(MotionModel)), "models",
                 self.models, f"a comma-separated list of {', '.join(get_args(MotionModel))}")
        _require(self.sample_frames >= 2, "sample_frames", self.sample_frames, "must be >= 2")
        _require(0 <= self.local_share <= 1, "local_share", self.local_share, "must lie in [0, 1]")
        _require(self.neighbours >= 8, "neighbours", self.neighbours, "must be >= 8 (a sample is 8 tracks)")
        _require(0 < self.preference_share < 1, "preference_share", self.preference_share, "must lie in (0, 1)")
        _require(self.max_motions >= 1, "max_motions", self.max_motions, "must be >= 1")
        _require(self.guided_rounds >= 0, "guided_rounds", self.guided_rounds, "must be >= 0")
        _require(self.links >= 1, "links", self.links, "must be >= 1")
        _require(self.pieces >= self.max_motions, "pieces", self.pieces, "must be >= max_motions")
        _require(self.link_floor > 0, "link_floor", self.link_floor, "must be > 0")
        _require(self.min_link_drop >= 1, "min_link_drop", self.min_link_drop, "must be >= 1")
        _require(self.support >= 1, "support", self.support, "must be >= 1")
        _require(self.outlier_factor > 1, "outlier_factor", self.outlier_factor, "must be > 1")
        _require(self.restarts >= 1, "restarts", self.restarts, "must be >= 1")
        _require(self.kmeans_iterations >= 1, "kmeans_iterations", self.kmeans_iterations, "must be >= 1")
        _require(self.min_frames >= 2, "min_frames", self.min_frames, "must be >= 2")


@dataclass(frozen=True)
class ChessboardConfig:
    """Chessboard corner detection (see :mod:`torchsfm.calibration.chessboard`).

    Candidates are found on a copy whose long side is at most ``detection_size`` px, smoothed by
    a Gaussian of ``sigma`` px: local maxima of the saddle response within ``nms_radius`` px,
    above ``relative_threshold`` × its maximum, at most ``max_candidates``, that alternate
    dark/bright four times on a circle of ``junction_radius`` px with at least ``min_contrast``
    (intensities in [0, 1]). The lattice grows from up to ``seeds`` seeds and takes a candidate
    within ``search_radius`` × the local corner spacing of its prediction; up to ``max_missing``
    corners may be filled in, and lattice nodes beyond the pattern are dropped as stray if their
    saddle response is below ``stray_strength`` × the board's. Sub-pixel refinement uses a window of 0.3 × the spacing (at most
    ``max_half_window`` px each side).
    """

    detection_size: int = 1000
    sigma: float = 1.5
    nms_radius: int = 3
    relative_threshold: float = 0.01
    max_candidates: int = 600
    junction_radius: float = 4.0
    min_contrast: float = 0.1
    seeds: int = 30
    search_radius: float = 0.3
    max_missing: int = 2
    stray_strength: float = 0.3
    max_half_window: int = 10

    def __post_init__(self) -> None:
        _require(self.detection_size >= 64, "detection_size", self.detection_size, "must be >= 64")
        _require(self.sigma > 0, "sigma", self.sigma, "must be > 0")
        _require(self.nms_radius >= 1, "nms_radius", self.nms_radius, "must be >= 1")
        _require(0 <= self.relative_threshold < 1, "relative_threshold", self.relative_threshold, "must lie in [0, 1)")
        _require(self.max_candidates >= 4, "max_candidates", self.max_candidates, "must be >= 4")
        _require(self.junction_radius > 0, "junction_radius", self.junction_radius, "must be > 0")
        _require(0 <= self.min_contrast < 1, "min_contrast", self.min_contrast, "must lie in [0, 1)")
        _require(self.seeds >= 1, "seeds", self.seeds, "must be >= 1")
        _require(0 < self.search_radius < 0.5, "search_radius", self.search_radius, "must lie in (0, 0.5)")
        _require(self.max_missing >= 0, "max_missing", self.max_missing, "must be >= 0")
        _require(0 <= self.stray_strength <= 1, "stray_strength", self.stray_strength, "must lie in [0, 1]")
        _require(self.max_half_window >= 2, "max_half_window", self.max_half_window, "must be >= 2")


@dataclass(frozen=True)
class CalibrationConfig:
    """Zhang's planar calibration (thesis Appendix A): per-view homographies by the normalized DLT
    refined by LM, the closed form for K, the extrinsics, then one LM (``lm``; Marquardt damping,
    since focal lengths and distortion differ by orders of magnitude) over fx, fy, cx, cy, k1, k2
    and every pose. ``min_views`` boards are needed. With ``zero_skew`` (OpenCV's model) the skew
    from the closed form is dropped before the LM.
    """

    chessboard: ChessboardConfig = field(default_factory=ChessboardConfig)
    lm: LMConfig = field(default_factory=lambda: LMConfig(damping="diagonal", initial_damping=1e-3, cost_tolerance=1e-10))
    min_views: int = 3
    zero_skew: bool = True

    def __post_init__(self) -> None:
        _require(self.min_views >= 3, "min_views", self.min_views, "must be >= 3 (Zhang's method)")


@dataclass(frozen=True)
class Config:
    """Every tunable of torchsfm, grouped by stage."""

    harris: HarrisConfig = field(default_factory=HarrisConfig)
    matching: MatchingConfig = field(default_factory=MatchingConfig)

    fundamental: FundamentalConfig = field(default_factory=FundamentalConfig)
    relative_pose: RelativePoseConfig = field(default_factory=RelativePoseConfig)
    triangulation: TriangulationConfig = field(default_factory=TriangulationConfig)
    lm: LMConfig = field(default_factory=LMConfig)
    two_view: TwoViewConfig = field(default_factory=TwoViewConfig)
    bundle_adjustment: BundleAdjustmentConfig = field(default_factory=BundleAdjustmentConfig)
    resection: ResectionConfig = field(default_factory=ResectionConfig)
    pairs: PairsConfig = field(default_factory=PairsConfig)
    reconstruction: ReconstructionConfig = field(default_factory=ReconstructionConfig)
    moving_objects: MovingObjectsConfig = field(default_factory=MovingObjectsConfig)
    segmentation: SegmentationConfig = field(default_factory=SegmentationConfig)
    calibration: CalibrationConfig = field(default_factory=CalibrationConfig)


def _build(cls: type, values: Any, prefix: str) -> Any:
    """Build dataclass ``cls`` from a mapping, recursing into nested dataclasses, strictly."""
    if not isinstance(values, dict):
        raise ConfigError(f"config {prefix.rstrip('.') or 'root'} must be a mapping, got {type(values).__name__}")
    hints = get_type_hints(cls)
    known = {f.name for f in dataclasses.fields(cls)}
    kwargs = {}
    for key, value in values.items():
        full_key = f"{prefix}{key}"
        if key not in known:
            raise ConfigError(f"unknown config key {full_key!r} (known here: {', '.join(sorted(known))})")
        hint = hints[key]
        if dataclasses.is_dataclass(hint):
            kwargs[key] = _build(hint, value, f"{full_key}.")
        else:
            kwargs[key] = _coerce(value, hint, full_key)
    try:
        return cls(**kwargs)
    except ConfigError as error:
        raise ConfigError(str(error).replace("config ", f"config {prefix}", 1)) from None


def _coerce(value: Any, hint: type, key: str) -> Any:
    if hint is bool:
        if isinstance(value, bool):
            return value
    elif hint is int:
        if isinstance(value, int) and not isinstance(value, bool):
            return value
    elif hint is float:
        if isinstance(value, (int, float)) and not isinstance(value, bool):
            return float(value)
        if isinstance(value, str):  # YAML 1.1 reads 1e-3 (no dot) as a string
            try:
                return float(value)
            except ValueError:
                pass
    elif hint is str:
        if isinstance(value, str):
            return value
    elif get_origin(hint) is Literal:  # a named choice: its section checks the name
        if isinstance(value, str):
            return value
        raise ConfigError(f"config {key}={value!r} must be one of {', '.join(get_args(hint))}")
    raise ConfigError(f"config {key}={value!r} must be of type {hint.__name__}")


def config_from_dict(values: dict) -> Config:
    """Build a :class:`Config` from nested mappings; missing keys keep their defaults."""
    return _build(Config, values, "")


def config_to_dict(config: Any) -> dict:
    """The nested-dict form of a config dataclass (what ``configs/default.yaml`` holds)."""
    return dataclasses.asdict(config)


def load_config(path: str | Path) -> Config:
    """Read a YAML file into a :class:`Config` (strict: unknown keys are errors)."""
    path = Path(path)
    try:
        text = path.read_text()
    except OSError as error:
        raise ConfigError(f"cannot read config file {path}: {error.strerror}") from None
    try:
        values = yaml.safe_load(text) or {}
    except yaml.YAMLError as error:
        raise ConfigError(f"config file {path} is not valid YAML: {error}") from None
    return config_from_dict(values)


def with_overrides(config: Config, assignments: list[str]) -> Config:
    """Apply ``section.key=value`` strings (values parsed as YAML scalars) to ``config``."""
    values = config_to_dict(config)
    for assignment in assignments:
        key, sep, raw = assignment.partition("=")
        if not sep or not key.strip():
            raise ConfigError(f"override {assignment!r} must look like section.key=value")
        *parents, leaf = key.strip().split(".")
        node = values
        for depth, part in enumerate(parents):
            if not isinstance(node.get(part), dict):
                raise ConfigError(f"unknown config key {'.'.join(parents[: depth + 1])!r} in override {assignment!r}")
            node = node[part]
        if leaf not in node:
            raise ConfigError(f"unknown config key {key.strip()!r} in override {assignment!r}")
        try:
            node[leaf] = yaml.safe_load(raw)
        except yaml.YAMLError as error:
            raise ConfigError(f"override {assignment!r}: the value is not a YAML scalar ({error})") from None
    return config_from_dict(values)
