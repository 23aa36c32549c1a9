"""Input checks shared by the modules that take user arrays."""

from __future__ import annotations

from typing import Any

import torch
from torch import Tensor

from ptrack.errors import InputError


def as_float_tensor(value: Any, name: str, like: Tensor | None = None) -> Tensor:
    """`value` as a real floating tensor: integers go to the default float dtype (or `like`'s
    dtype/device when given). Non-numeric, boolean or complex input raises InputError naming `name`."""
    try:
        x = torch.as_tensor(value)
    except (TypeError, ValueError, RuntimeError) as e:
        raise InputError(f"{name} is not numeric: {e}") from e
    if x.dtype == torch.bool or x.is_complex():
        raise InputError(f"{name} must be real numbers, got dtype {x.dtype}")
    if like is not None:
        return x.to(dtype=like.dtype, device=like.device)
    return x if x.is_floating_point() else x.to(torch.get_default_dtype())
