"""Thesis Table 3.1: NCC alone is ambiguous on repetitive texture.

On a fountain-P11 pair (the brick wall repeats), the final inlier matches of the two-view
pipeline serve as ground truth. Eight of them are chosen greedily to be as alike as possible;
the table shows the NCC of each image-1 patch (columns) with each image-2 patch (rows), as in
the thesis: the diagonal holds the true matches, high off-diagonal scores are the ambiguity.
Below it, over all matched corners: how often a wrong corner inside the search disc scores
above the NCC threshold, and how often it even beats the true match.

    python examples/ncc_ambiguity.py [--pair 0 1]
"""

from __future__ import annotations

import argparse

import torch

from torchsfm.config import Config
from torchsfm.io.datasets import read_strecha
from torchsfm.images import read_image, to_grey
from torchsfm.matching.ncc import extract_patches, ncc_table
from torchsfm.sfm.two_view import TwoViewReconstruction

from ncc_vs_strength import DEFAULT_DATA


def most_alike(similarity: torch.Tensor, count: int) -> list[int]:
    """Greedy set of ``count`` indices with the largest mutual off-diagonal similarity."""
    off_diagonal = similarity - torch.diag(torch.diagonal(similarity))
    chosen = [int(off_diagonal.amax(1).argmax())]
    while len(chosen) < count:
        score = (off_diagonal[:, chosen] + off_diagonal[chosen, :].T).mean(-1)
        score[chosen] = float("-inf")
        chosen.append(int(score.argmax()))
    return chosen


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--pair", type=int, nargs=2, default=(0, 1))
    args = parser.parse_args()
    sequence = read_strecha(DEFAULT_DATA / "strecha_fountain_P11")
    i, j = args.pair
    image1, image2 = read_image(sequence.images[i]), read_image(sequence.images[j])
    config = Config()
    model = TwoViewReconstruction(config)(image1, image2, sequence.K[i], sequence.K[j], generator=torch.Generator().manual_seed(0))
    x1, x2 = model.matches[model.inlier_mask, :2].float(), model.matches[model.inlier_mask, 2:].float()
    grey1, grey2 = to_grey(image1), to_grey(image2)
    half = config.matching.patch_half_size
    similarity = extract_patches(grey2, x2, half) @ extract_patches(grey1, x1, half).T  # rows image 2, columns image 1
    chosen = most_alike(similarity, 8)
    print(f"fountain-P11 {i}-{j}: NCC of 8 true matches' patches (columns: image {i}, rows: image {j}; diagonal = true match)")
    for row in chosen:
        print(" ".join(f"{similarity[row, column]:7.4f}" + ("*" if row == column else " ") for column in chosen))
    disc = torch.cdist(x1, x2) < config.matching.search_radius
    ncc = torch.where(disc, ncc_table(grey1, grey2, x1, x2, half), float("-inf"))  # (M, M) within the disc
    true_score = torch.diagonal(ncc)
    wrong = ncc.clone()
    wrong.fill_diagonal_(float("-inf"))
    ambiguous = (wrong > config.matching.ncc_threshold).any(1)
    beaten = wrong.amax(1) > true_score
    print(f"\nover all {x1.shape[0]} matched corners: {ambiguous.double().mean():.1%} have a wrong corner in the "
          f"{config.matching.search_radius:.0f} px disc with NCC > {config.matching.ncc_threshold}; "
          f"for {beaten.double().mean():.1%} a wrong corner scores higher than the true match")


if __name__ == "__main__":
    main()
