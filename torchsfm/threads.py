"""Independent pieces of torch work side by side: one Python thread each, one intra-op thread each."""

from __future__ import annotations

import threading
from collections.abc import Callable, Iterable
from concurrent.futures import ThreadPoolExecutor
from typing import ParamSpec, TypeVar

import torch

Item = TypeVar("Item")
Result = TypeVar("Result")
Arguments = ParamSpec("Arguments")


def map_in_threads(function: Callable[[Item], Result], items: Iterable[Item]) -> list[Result]:
    """``[function(item) for item in items]``, computed ``torch.get_num_threads()`` items at a
    time, each on a thread of its own with one intra-op thread (restored afterwards).

    For many small, independent problems (one view pair's matching: hundreds of tensor operations
    on a few thousand elements each) the operations are too small to share out, so one thread per
    problem keeps the cores busy where the intra-op threads would wait on Python. The results are
    those of the loop, in the items' order, whatever the threads' timing; the first exception
    raised is raised here. The threads run in the caller's inference mode (a thread-local
    setting that a new thread would not inherit). With one thread: the plain loop."""
    items = list(items)
    workers = min(torch.get_num_threads(), len(items))
    if workers <= 1:
        return [function(item) for item in items]
    inference = torch.is_inference_mode_enabled()

    def in_callers_mode(item: Item) -> Result:
        with torch.inference_mode(inference):
            return function(item)

    intra_op = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        with ThreadPoolExecutor(workers) as pool:
            return list(pool.map(in_callers_mode, items))
    finally:
        torch.set_num_threads(intra_op)


def one_at_a_time(function: Callable[Arguments, Result]) -> Callable[Arguments, Result]:
    """``function`` behind a lock: calls from the threads of :func:`map_in_threads` (a progress
    report, say) run one after another, never interleaved."""
    lock = threading.Lock()

    def locked(*args: Arguments.args, **kwargs: Arguments.kwargs) -> Result:
        with lock:
            return function(*args, **kwargs)

    return locked
