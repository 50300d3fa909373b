"""Command line: ``torchsfm demo | two-view | reconstruct``. Thin: parse, then call :mod:`torchsfm.actions`.

Progress goes to stderr; any torchsfm error becomes one line ``torchsfm: error: ...`` on stderr
and exit status 2, with no output files written.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

from torchsfm.errors import InputError, TorchSfmError


def _progress(quiet: bool):
    start = time.perf_counter()

    def report(message: str) -> None:
        if not quiet:
            print(f"[{time.perf_counter() - start:6.2f} s] {message}", file=sys.stderr, flush=True)

    return report


def _config(args: argparse.Namespace):
    from torchsfm.config import Config, load_config, with_overrides

    config = load_config(args.config) if args.config else Config()
    flags = (["moving_objects.enabled=true"] if args.moving_objects else []) + (
        ["moving_objects.reconstruct_objects=true"] if args.moving_objects == "reconstruct" else []) + (
        ["pairs.mode=sequential"] if getattr(args, "sequential", False) else [])
    return with_overrides(config, args.set + flags)


def _print_summary(summary: dict, out: Path) -> None:
    print(f"{summary['images'][0]} + {summary['images'][1]}: {summary['putative_matches']} putative matches, "
          f"{summary['inliers']} inliers, {summary['points']} points, reprojection RMS {summary['reprojection_rms_px']:.3f} px, "
          f"{summary['seconds']['total']:.2f} s")
    if "ground_truth" in summary:
        truth = summary["ground_truth"]
        print(f"against the ground truth: rotation error {truth['rotation_error_deg']:.3f} deg, "
              f"translation direction error {truth['translation_direction_error_deg']:.3f} deg")
    _print_moving_objects(summary)
    print(f"wrote {out}/model.wrl, points.ply, colmap/, matches.png, summary.json")


def _print_moving_objects(summary: dict) -> None:
    for triplet in summary.get("moving_objects", []):
        note = f" (IMOR skipped: {triplet['fallback']})" if triplet["fallback"] else ""
        print(f"views {triplet['views']}: {triplet['vectors']} vectors, IMOR rejected {triplet['imor_rejected']}, "
              f"RANSAC rejected {triplet['ransac_rejected']} more, {triplet['background']} kept as static{note}")
    per_view = summary.get("moving_observations_rejected_per_view", [])
    if per_view:
        print("observations rejected as moving (or untestable) per view: "
              + ", ".join(f"{row['index']}: {row['rejected']}" for row in per_view))


def _demo(args: argparse.Namespace) -> None:
    from torchsfm.actions import demo

    _print_summary(demo(args.out, progress=_progress(args.quiet)), args.out)


def _two_view(args: argparse.Namespace) -> None:
    from torchsfm.actions import two_view
    from torchsfm.calibration.files import read_camera

    if args.moving_objects == "reconstruct":
        raise InputError("--moving-objects reconstruct needs the frames of a sequence: use 'torchsfm reconstruct'")
    config = _config(args)
    K, distortion = read_camera(args.K)
    summary = two_view(args.image1, args.image2, K, args.out, distortion=distortion, config=config, third=args.third,
                       seed=args.seed, progress=_progress(args.quiet))
    _print_summary(summary, args.out)


def _reconstruct(args: argparse.Namespace) -> None:
    from torchsfm.actions import reconstruct_sequence
    from torchsfm.calibration.files import read_camera

    config = _config(args)
    K, distortion = read_camera(args.K) if args.K is not None else (None, None)
    summary = reconstruct_sequence(args.images, K, args.out, distortion=distortion, config=config, seed=args.seed,
                                   progress=_progress(args.quiet), masks=args.masks)
    if args.K is None:
        K = summary["K"]
        print(f"estimated intrinsics: f {K[0][0]:.1f} px, principal point ({K[0][2]:.1f}, {K[1][2]:.1f})")
    print(f"{summary['views_registered']} views registered, {summary['points']} points, mean track length "
          f"{summary['mean_track_length']:.2f}, reprojection RMS {summary['reprojection_rms_px']:.3f} px, "
          f"{summary['seconds']['total']:.1f} s")
    for view in summary["unregistered"]:
        print(f"view {view['index']} not registered: {view['reason']}")
    for view in summary["loose_resections"]:
        print(f"view {view['index']} registered at a widened resection threshold of {view['threshold_px']:g} px (less certain)")
    for view in summary["tracked_resections"]:
        print(f"view {view['index']} registered by tracking against the map ({view['inliers']} inliers among the model's points "
              "found where a resection at a widened threshold put them)")
    for view in summary["still_frames"]:
        print(f"view {view['index']}: the camera did not move from view {view['keyframe']}; resected from the model, not adjusted")
    _print_moving_objects(summary)
    for body in summary["objects"]:
        print(f"moving body {body['label']} ({body['tracks']} tracks): " + (
            f"{len(body['views'])} views, {body['points']} points in {args.out}/{body['folder']}/ (its own scale)"
            if "folder" in body else body["reason"]))
    print(f"wrote {args.out}/model.wrl, points.ply, colmap/, summary.json")


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="torchsfm", description="Structure from motion with PyTorch.")
    commands = parser.add_subparsers(dest="command", required=True)

    demo = commands.add_parser("demo", help="reconstruct the two bundled fountain-P11 images")
    demo.add_argument("--out", type=Path, default=Path("torchsfm_demo"), help="output folder (default: torchsfm_demo)")
    demo.add_argument("--quiet", action="store_true", help="no progress messages")
    demo.set_defaults(run=_demo)

    two_view = commands.add_parser("two-view", help="reconstruct two calibrated images")
    two_view.add_argument("image1", type=Path)
    two_view.add_argument("image2", type=Path)
    two_view.add_argument("--third", type=Path, help="the frame after image2 (needed by --moving-objects)")
    _job_options(two_view)
    two_view.set_defaults(run=_two_view)

    sequence = commands.add_parser("reconstruct", help="reconstruct a calibrated image sequence")
    sequence.add_argument("images", nargs="+", type=Path, help="image files and/or folders of images, in sequence order")
    _job_options(sequence, K_required=False)
    sequence.add_argument("--sequential", action="store_true",
                          help="a video: match each frame with the next pairs.window frames only (pairs.mode=sequential)")
    sequence.add_argument("--masks", type=Path, help="where features may be detected (not where black): one mask image for "
                          "every image (a video's time stamp or logo), or a folder of masks named <image file name>.png (COLMAP's)")
    sequence.set_defaults(run=_reconstruct)

    calibrate = commands.add_parser("calibrate", help="calibrate a camera from chessboard photos (Zhang's method)")
    calibrate.add_argument("images", nargs="+", type=Path, help="chessboard photos and/or folders of them")
    calibrate.add_argument("--pattern", required=True, type=_pattern, help="inner corners per row x per column, e.g. 9x7")
    calibrate.add_argument("--square", type=float, default=1.0, help="side of a square (sets the unit of the poses)")
    calibrate.add_argument("--out", required=True, type=Path, help="calibration file to write, e.g. calib.yaml")
    calibrate.add_argument("--config", type=Path, help="YAML config (defaults: configs/default.yaml)")
    calibrate.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="override one config value")
    calibrate.add_argument("--quiet", action="store_true", help="no progress messages")
    calibrate.set_defaults(run=_calibrate, moving_objects=None)
    return parser


def _pattern(text: str) -> tuple[int, int]:
    try:
        cols, rows = (int(part) for part in text.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"pattern must look like 9x7, got {text!r}") from None
    if cols < 2 or rows < 2:
        raise argparse.ArgumentTypeError(f"a pattern needs at least 2x2 inner corners, got {text!r}")
    return cols, rows


def _calibrate(args: argparse.Namespace) -> None:
    from torchsfm.actions import calibrate

    summary = calibrate(args.images, args.pattern, args.square, args.out, config=_config(args), progress=_progress(args.quiet))
    K = summary["K"]
    print(f"{len(summary['views'])} views: fx {K[0][0]:.2f}, fy {K[1][1]:.2f}, cx {K[0][2]:.2f}, cy {K[1][2]:.2f}, "
          f"k1 {summary['distortion'][0]:.5f}, k2 {summary['distortion'][1]:.5f}, reprojection RMS {summary['rms_px']:.3f} px")
    for view in summary["not_found"]:
        print(f"no board in {view['image']}: {view['reason']}")
    print(f"wrote {args.out} and the detected corners in {summary['corners_folder']}/")


def _job_options(parser: argparse.ArgumentParser, *, K_required: bool = True) -> None:
    """The options every reconstruction command takes."""
    parser.add_argument("--K", required=K_required, type=Path,
                        help="camera file: 3x3 K as text (optionally a 4th row 'k1 k2'), or a calib.yaml from 'torchsfm calibrate'"
                        + ("" if K_required else "; without it the focal length and principal point are estimated"))
    parser.add_argument("--config", type=Path, help="YAML config (defaults: configs/default.yaml)")
    parser.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="override one config value")
    parser.add_argument("--out", required=True, type=Path, help="output folder")
    parser.add_argument("--seed", type=int, default=0, help="seed of every random choice")
    parser.add_argument("--moving-objects", nargs="?", const="reject", choices=("reject", "reconstruct"),
                        help="reject independently moving objects (IMOR + RANSAC over frame triplets); 'reconstruct' "
                        "(multi-view): segment the motions and reconstruct each moving body as its own model")
    parser.add_argument("--quiet", action="store_true", help="no progress messages")


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        args.run(args)
    except TorchSfmError as error:
        print(f"torchsfm: error: {error}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
