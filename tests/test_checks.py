"""ptrack.checks.as_float_tensor."""

import pytest
import torch

from ptrack.checks import as_float_tensor
from ptrack.errors import InputError


def test_integers_become_default_float_and_like_sets_dtype():
    assert as_float_tensor([1, 2], "x").dtype == torch.get_default_dtype()
    like = torch.zeros(1, dtype=torch.float64)
    assert as_float_tensor([1.5], "x", like=like).dtype == torch.float64
    x = torch.ones(2, dtype=torch.float64)
    assert as_float_tensor(x, "x") is x


@pytest.mark.parametrize("bad", ["abc", [True, False], torch.tensor([1 + 2j])])
def test_bad_values_name_the_argument(bad):
    with pytest.raises(InputError, match="weights"):
        as_float_tensor(bad, "weights")
