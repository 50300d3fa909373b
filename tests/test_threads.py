"""map_in_threads: the loop's results, in order, side by side."""

from __future__ import annotations

import pytest
import torch
from torch.testing import assert_close

from torchsfm.threads import map_in_threads, one_at_a_time


def _work(seed: int) -> torch.Tensor:
    generator = torch.Generator().manual_seed(seed)
    a = torch.randn(200, 121, generator=generator)
    return (a @ a.T).topk(5, dim=1).values.sum(0)


@pytest.fixture
def two_threads():
    threads = torch.get_num_threads()
    torch.set_num_threads(2)
    yield
    torch.set_num_threads(threads)


def test_results_are_the_loops_in_the_items_order(two_threads):
    expected = [_work(seed) for seed in range(7)]
    for result, reference in zip(map_in_threads(_work, range(7)), expected, strict=True):
        assert_close(result, reference, rtol=0, atol=0)


def test_the_intra_op_threads_are_restored_even_after_an_exception(two_threads):
    def fails_on_three(item: int) -> int:
        if item == 3:
            raise ValueError("item 3 is bad")
        return item

    with pytest.raises(ValueError, match="item 3 is bad"):
        map_in_threads(fails_on_three, range(6))
    assert torch.get_num_threads() == 2
    assert map_in_threads(lambda item: torch.get_num_threads(), range(4)) == [1, 1, 1, 1]  # one intra-op thread each
    assert torch.get_num_threads() == 2


def test_one_thread_is_the_plain_loop():
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        assert map_in_threads(lambda item: item * 2, [1, 2, 3]) == [2, 4, 6]
        assert map_in_threads(lambda item: item, []) == []
    finally:
        torch.set_num_threads(threads)


def test_one_at_a_time_serializes_the_calls(two_threads):
    inside, overlaps = [0], []

    def report(message: str) -> str:
        inside[0] += 1
        overlaps.append(inside[0])
        sum(range(20000))  # long enough for another thread to come in
        inside[0] -= 1
        return message

    locked = one_at_a_time(report)
    assert map_in_threads(locked, [f"m{k}" for k in range(40)]) == [f"m{k}" for k in range(40)]
    assert max(overlaps) == 1


def test_the_threads_run_in_the_callers_inference_mode(two_threads):
    def mode(_: int) -> bool:
        return torch.is_inference_mode_enabled()

    with torch.inference_mode():
        assert map_in_threads(mode, range(4)) == [True] * 4
    assert map_in_threads(mode, range(4)) == [False] * 4
