"""Verifying the matched view pairs of a Strecha sequence: one ragged batched
``estimate_fundamental(..., valid=)`` call against one call per pair (same config, medians of 3).

    python benchmarks/pair_verification.py [--data ../shared/data]
"""

from __future__ import annotations

import argparse
import statistics
import time
from pathlib import Path

import torch

import torchsfm
from torchsfm.config import Config
from torchsfm.images import read_image
from torchsfm.io.datasets import read_strecha
from torchsfm.sfm.stages import ViewSet, default_pipeline

DEFAULT_DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"


def median_seconds(function, repeats: int = 3) -> float:
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        function()
        times.append(time.perf_counter() - start)
    return statistics.median(times)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path, default=DEFAULT_DATA)
    args = parser.parse_args()
    config = Config()
    for name in ("strecha_fountain_P11", "strecha_herzjesu_P8"):
        sequence = read_strecha(args.data / name)
        state = default_pipeline(config)[:2](ViewSet.of([read_image(p) for p in sequence.images], sequence.K))
        pairs = [(state.corners[i][a], state.corners[j][b]) for (i, j), (a, b) in state.putative.items()]
        size = max(x1.shape[0] for x1, _ in pairs)
        x1 = torch.zeros(len(pairs), size, 2, dtype=torch.float64)
        x2 = torch.zeros_like(x1)
        valid = torch.zeros(len(pairs), size, dtype=torch.bool)
        for b, (p1, p2) in enumerate(pairs):
            x1[b, : p1.shape[0]], x2[b, : p1.shape[0]], valid[b, : p1.shape[0]] = p1, p2, True

        def one_by_one() -> None:
            for p1, p2 in pairs:
                try:
                    torchsfm.estimate_fundamental(p1, p2, config=config, generator=torch.Generator().manual_seed(0))
                except torchsfm.TorchSfmError:
                    pass

        batched = median_seconds(lambda: torchsfm.estimate_fundamental(x1, x2, valid=valid, config=config,
                                                                         generator=torch.Generator().manual_seed(0)))
        single = median_seconds(one_by_one)
        print(f"{name}: {len(pairs)} pairs (up to {size} matches): one ragged batch {batched:.2f} s, "
              f"one call per pair {single:.2f} s, ratio {batched / single:.2f}")


if __name__ == "__main__":
    main()
