import torch
from torch.testing import assert_close

from torchsfm.geometry.small_linalg import smallest_eigenvector_sym3, symmetric_eigenvalues3

DOUBLE = dict(dtype=torch.float64)


def _symmetric(n=500, seed=0):
    A = torch.randn(n, 3, 3, generator=torch.Generator().manual_seed(seed), **DOUBLE)
    return A.transpose(-1, -2) @ A


def test_eigenvalues_match_lapack():
    M = _symmetric()
    assert_close(symmetric_eigenvalues3(M), torch.linalg.eigvalsh(M), rtol=0, atol=1e-11)


def test_smallest_eigenvector_matches_lapack_up_to_sign():
    M = _symmetric()
    v = smallest_eigenvector_sym3(M)
    reference = torch.linalg.eigh(M).eigenvectors[..., 0]
    assert_close((v * reference).sum(-1).abs(), torch.ones(500, **DOUBLE), rtol=0, atol=1e-9)
