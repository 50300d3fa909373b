"""Command line: ``torchsfm demo``. Library-first: each command calls public functions.

Errors raised by torchsfm become one line on stderr and exit status 2.
"""

from __future__ import annotations

import argparse
import sys

from torchsfm.errors import TorchSfmError


def _demo(args: argparse.Namespace) -> None:
    from torchsfm.demo import print_demo, run_demo

    print_demo(run_demo(outliers=args.outliers, seed=args.seed), args.outliers)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="torchsfm", description="Structure from motion with PyTorch.")
    commands = parser.add_subparsers(dest="command", required=True)
    demo = commands.add_parser("demo", help="robust two-view geometry on the bundled sample data")
    demo.add_argument("--outliers", type=float, default=0.4, help="fraction of matches replaced by random pixels")
    demo.add_argument("--seed", type=int, default=0)
    demo.set_defaults(run=_demo)
    return parser


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
