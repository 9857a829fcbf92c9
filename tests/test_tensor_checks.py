"""all_finite: the cheap check every weights receiver runs must say exactly what the element-wise one says."""

from __future__ import annotations

import pytest
import torch

from romannet.common.tensor_checks import all_finite

NAN, INF = float("nan"), float("inf")


@pytest.mark.parametrize("dtype", [torch.float32, torch.bfloat16, torch.float16, torch.float64])
@pytest.mark.parametrize("values, finite", [
    ([0.0, 1.5, -2.0], True),
    ([1.0, NAN], False),
    ([INF, 1.0], False),
    ([-INF, 1.0], False),
    ([INF, -INF], False),  # their sum is NaN, not a number that hides them
    ([NAN, INF, -INF], False),
    ([], True),
])
def test_agrees_with_the_element_wise_check(dtype, values, finite):
    t = torch.tensor(values, dtype=dtype)
    assert all_finite(t) is finite
    assert all_finite(t) == bool(torch.isfinite(t).all())


@pytest.mark.parametrize("dtype", [torch.float32, torch.bfloat16, torch.float16])
def test_finite_values_whose_sum_overflows_are_finite(dtype):
    big = torch.finfo(dtype).max
    t = torch.full((64,), big, dtype=dtype)
    assert not torch.isfinite(t.sum())  # the fast path cannot settle it ...
    assert all_finite(t)  # ... so the element-wise check does
    t[7] = NAN
    assert not all_finite(t)


def test_integer_and_complex_tensors():
    assert all_finite(torch.arange(5))
    assert all_finite(torch.tensor([True, False]))
    assert all_finite(torch.tensor([1 + 2j]))
    assert not all_finite(torch.tensor([complex(1, NAN)]))
