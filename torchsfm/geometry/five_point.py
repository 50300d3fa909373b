"""The five-point essential matrix (Stewénius, Engels & Nistér 2006), batched (ours).

Five correspondences in normalized camera coordinates give a 4-dimensional null space of the
epipolar constraints, E = x X + y Y + z Z + W. The essential matrix constraints — det E = 0 and
2 E Eᵀ E − tr(E Eᵀ) E = 0 — are ten cubics in (x, y, z) over 20 monomials. Eliminating their ten
cubic monomials (one batched solve of the 10 × 10 block) expresses each cubic through the ten
monomials of degree <= 2; multiplying that basis by x lands in it or on an eliminated cubic,
which gives the action matrix of x (Stewénius et al. order the monomials grevlex; any order of
the cubics within their degree gives the same matrix). Its real eigenvectors are the basis
monomials evaluated at the (up to ten) real solutions.
"""

from __future__ import annotations

import itertools

import torch
from torch import Tensor

MAX_SOLUTIONS = 10


def _monomials(degree: int) -> list[tuple[int, int, int, int]]:
    """Exponents (x, y, z, w) of the homogeneous monomials of a degree, w the homogenizing
    variable (the constant), by decreasing degree in (x, y, z) and lexicographically (x > y > z)
    within it: x³, x²y, x²z, xy², xyz, xz², y³, y²z, yz², z³, x², xy, ..., z, 1 for degree 3."""
    exponents = [e for e in itertools.product(range(degree + 1), repeat=4) if sum(e) == degree]
    return sorted(exponents, key=lambda e: (-(e[0] + e[1] + e[2]), [-value for value in e[:3]]))


MONOMIALS = {degree: _monomials(degree) for degree in (1, 2, 3)}


def _product_table(a: int, b: int) -> Tensor:
    """(n_a, n_b, n_(a+b)) 0/1: monomial i of degree a times monomial j of degree b."""
    index = {e: k for k, e in enumerate(MONOMIALS[a + b])}
    table = torch.zeros(len(MONOMIALS[a]), len(MONOMIALS[b]), len(MONOMIALS[a + b]), dtype=torch.float64)
    for i, p in enumerate(MONOMIALS[a]):
        for j, q in enumerate(MONOMIALS[b]):
            table[i, j, index[tuple(u + v for u, v in zip(p, q))]] = 1.0
    return table


PRODUCTS = {(1, 1): _product_table(1, 1), (2, 1): _product_table(2, 1)}


def _times(p: Tensor, q: Tensor, degrees: tuple[int, int]) -> Tensor:
    """Product of polynomials (..., n_a) and (..., n_b) of the given degrees -> (..., n_(a+b))."""
    table = PRODUCTS[degrees].to(p)
    return torch.einsum("...i,...j,ijk->...k", p, q, table)


def essential_constraints(basis: Tensor) -> Tensor:
    """(*, 4, 3, 3) null-space basis X, Y, Z, W -> (*, 10, 20) coefficients of the ten cubic
    constraints on E = x X + y Y + z Z + W over the degree-3 monomials (``MONOMIALS[3]``)."""
    E = basis.permute(*range(basis.dim() - 3), -2, -1, -3)  # (*, 3, 3, 4): every entry linear in (x, y, z, 1)
    EEt = _times(E[..., :, None, :, :], E[..., None, :, :, :], (1, 1)).sum(-2)  # (*, 3, 3, 10): Σ_k E_ik E_jk
    trace = EEt.diagonal(dim1=-3, dim2=-2).sum(-1)  # (*, 10)
    EEtE = _times(EEt[..., :, :, None, :], E[..., None, :, :, :], (2, 1)).sum(-3)  # (*, 3, 3, 20): Σ_k (EEᵀ)_ik E_kj
    cubic = 2 * EEtE - _times(trace[..., None, None, :], E, (2, 1))

    def minor(a: int, b: int) -> Tensor:  # E_1a E_2b - E_1b E_2a, degree 2
        return _times(E[..., 1, a, :], E[..., 2, b, :], (1, 1)) - _times(E[..., 1, b, :], E[..., 2, a, :], (1, 1))

    minors = torch.stack([minor(1, 2), minor(0, 2), minor(0, 1)], -2)  # (*, 3, 10): the cofactors of row 0, unsigned
    signs = torch.tensor([1.0, -1.0, 1.0], dtype=basis.dtype, device=basis.device)[:, None]
    determinant = (_times(minors, E[..., 0, :, :], (2, 1)) * signs).sum(-2)  # (*, 20): expansion along row 0
    return torch.cat([determinant[..., None, :], cubic.flatten(-3, -2)], -2)


# multiplication by x on the basis x², xy, xz, y², yz, z², x, y, z, 1 (columns 10..19 of MONOMIALS[3]):
# the first six products are the eliminated cubics x³, x²y, x²z, xy², xyz, xz² (columns and rows 0..5
# of the reduced system); the other four land on the basis
_SHIFTED = {6: 0, 7: 1, 8: 2, 9: 6}  # x·x = x², x·y = xy, x·z = xz, x·1 = x (basis positions)


def five_point_essential(x1: Tensor, x2: Tensor) -> tuple[Tensor, Tensor]:
    """Every essential matrix of five correspondences.

    Args:
        x1, x2: (*, 5, 2) normalized camera coordinates (K⁻¹ x), float64.

    Returns:
        E (*, 10, 3, 3) unit Frobenius norm and (*, 10) bool: which of the ten are real
        solutions (the others are NaN).
    """
    h1 = torch.cat([x1, torch.ones_like(x1[..., :1])], -1)
    h2 = torch.cat([x2, torch.ones_like(x2[..., :1])], -1)
    rows = (h2[..., :, None] * h1[..., None, :]).flatten(-2)  # (*, 5, 9): x2ᵀ E x1 = row · vec(E)
    padded = torch.cat([rows, torch.zeros_like(rows[..., :4, :])], -2)  # square: a full SVD's last four vectors
    basis = torch.linalg.svd(padded).Vh[..., 5:, :].reshape(*rows.shape[:-2], 4, 3, 3)  # X, Y, Z, W
    constraints = essential_constraints(basis)
    reduced, info = torch.linalg.solve_ex(constraints[..., :10], constraints[..., 10:])  # (*, 10, 10)
    action = torch.zeros_like(reduced)
    action[..., :6, :] = -reduced[..., :6, :]
    for row, column in _SHIFTED.items():
        action[..., row, column] = 1.0
    values, vectors = torch.linalg.eig(action)  # vectors: the basis monomials at each solution
    vectors = vectors / vectors[..., 9:10, :]  # the constant monomial to 1
    real = (values.imag.abs() <= 1e-8 * values.abs().clamp_min(1.0)) & (info == 0)[..., None]
    xyz = vectors[..., 6:9, :].real.transpose(-1, -2)  # (*, 10, 3)
    E = (xyz[..., :, :, None, None] * basis[..., None, :3, :, :]).sum(-3) + basis[..., None, 3, :, :]
    E = E / E.flatten(-2).norm(dim=-1)[..., None, None]
    real &= torch.isfinite(E).flatten(-2).all(-1)
    return torch.where(real[..., None, None], E, torch.nan), real
