"""The public entry points run in ``torch.inference_mode`` and hand back ordinary tensors.

None of them is differentiable (RANSAC draws, LM steps), so autograd's bookkeeping on each of
their thousands of small tensor operations (version counters, view tracking) is pure overhead:
measured at 18 % of one ``estimate_fundamental`` call on 1000 correspondences and 7-10 % of
``estimate_relative_pose`` (single-thread CPU time). Tensors made in inference mode refuse
in-place updates and autograd outside it, so what a decorated function returns is cloned into
ordinary tensors on the way out (a few small tensors; a model's arrays once).
"""

from __future__ import annotations

import dataclasses
import functools
from collections.abc import Callable
from typing import Any, ParamSpec, TypeVar

import torch
from torch import Tensor

Result = TypeVar("Result")
Arguments = ParamSpec("Arguments")


def ordinary_tensors(value: Any) -> Any:
    """``value`` with every inference-mode tensor in it replaced by an ordinary clone: tensors,
    dataclasses (fields updated in place), lists, tuples (named ones too) and dicts, nested; any
    other value as it is."""
    if isinstance(value, Tensor):
        return value.clone() if value.is_inference() else value
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        for item in dataclasses.fields(value):
            object.__setattr__(value, item.name, ordinary_tensors(getattr(value, item.name)))
        return value
    if isinstance(value, dict):
        return type(value)((key, ordinary_tensors(item)) for key, item in value.items())
    if isinstance(value, (list, tuple)):
        items = [ordinary_tensors(item) for item in value]
        return type(value)(*items) if hasattr(value, "_fields") else type(value)(items)
    return value


def without_autograd(function: Callable[Arguments, Result]) -> Callable[Arguments, Result]:
    """``function`` run in ``torch.inference_mode``, its result made of ordinary tensors
    (:func:`ordinary_tensors`). Called where inference mode is already on (from another entry
    point, or by a caller who chose it), it runs as it is and returns what it made."""

    @functools.wraps(function)
    def run(*args: Arguments.args, **kwargs: Arguments.kwargs) -> Result:
        if torch.is_inference_mode_enabled():
            return function(*args, **kwargs)
        with torch.inference_mode():
            result = function(*args, **kwargs)
        return ordinary_tensors(result)

    return run
