import pytest
import torch

from torchsfm.errors import InputError, NotEnoughDataError, ShapeError
from torchsfm.validation import check_finite, check_floating, check_min_count, check_shapes, count_distinct_rows, has_distinct_rows


def test_shapes_bind_names_across_arguments():
    sizes = check_shapes(x1=(torch.zeros(2, 5, 2), "* N 2"), x2=(torch.zeros(2, 5, 2), "* N 2"))
    assert sizes == {"N": 5}
    with pytest.raises(ShapeError, match="x2 has N=4 but x1 has N=5"):
        check_shapes(x1=(torch.zeros(5, 2), "* N 2"), x2=(torch.zeros(4, 2), "* N 2"))


def test_shapes_reject_wrong_literal_and_rank():
    with pytest.raises(ShapeError, match=r"K must have shape \(\*, 3, 3\), got \(3, 4\)"):
        check_shapes(K=(torch.zeros(3, 4), "* 3 3"))
    with pytest.raises(ShapeError, match="got \\(3,\\)"):
        check_shapes(K=(torch.zeros(3), "3 3"))
    with pytest.raises(InputError, match="torch.Tensor"):
        check_shapes(K=([[1.0]], "1 1"))


def test_finite_floating_and_counts():
    with pytest.raises(InputError, match="x holds 1 NaN"):
        check_finite(x=torch.tensor([1.0, float("nan")]))
    with pytest.raises(InputError, match="floating-point"):
        check_floating(x=torch.zeros(3, dtype=torch.long))
    with pytest.raises(InputError, match="x must be a torch.Tensor, got list"):
        check_floating(x=[1.0, 2.0])
    with pytest.raises(NotEnoughDataError, match="needs at least 8, got 7"):
        check_min_count("x1", 7, 8, "the 8-point algorithm")


def test_count_distinct_rows():
    x = torch.tensor([[1.0, 2.0], [1.0, 2.0], [2.0, 1.0], [1.0, 3.0], [2.0, 1.0]])
    assert count_distinct_rows(x) == 3
    assert count_distinct_rows(torch.zeros(0, 2)) == 0
    # a batch: every matrix counted on its own, equal to the count of its rows as tuples
    g = torch.Generator().manual_seed(0)
    batch = torch.randint(0, 3, (5, 40, 2), generator=g).double()
    expected = torch.tensor([len({tuple(row) for row in matrix.tolist()}) for matrix in batch])
    assert torch.equal(count_distinct_rows(batch), expected)
    assert torch.equal(count_distinct_rows(batch.reshape(5, 1, 40, 2)), expected.reshape(5, 1))


def test_has_distinct_rows_agrees_with_the_count():
    """Exact whether the distinct rows come early, only after the first 4k rows, or never."""
    g = torch.Generator().manual_seed(1)
    k = 8
    batch = torch.randint(0, 3, (6, 100, 2), generator=g).double()  # 9 possible rows: mostly >= 8 distinct
    batch[1] = 0.0  # one point repeated
    batch[2, : 4 * k] = 0.0  # the distinct rows only after the first 4k
    batch[3] = torch.tensor([[0.0, 0.0], [1.0, 0.0], [0.0, 1.0]]).repeat(34, 1)[:100]  # 3 distinct
    batch[4, : 4 * k] = 0.0
    batch[4, 4 * k:] = torch.arange(1.0, 8.0).repeat(10)[: 100 - 4 * k, None]  # 8 distinct in all ((0, 0) and 7 more), late
    expected = count_distinct_rows(batch) >= k
    assert expected.tolist() == [True, False, True, False, True, expected[5].item()]
    assert torch.equal(has_distinct_rows(batch, k), expected)
    assert torch.equal(has_distinct_rows(batch[[0, 5]], k), expected[[0, 5]])  # the early answer alone
