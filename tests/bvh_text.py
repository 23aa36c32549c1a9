"""Two BVH files compared as text: the same words, numbers within a tolerance (a run's BVH against its export)."""

from __future__ import annotations

import numpy as np


def assert_bvh_close(a: str, b: str, atol: float) -> None:
    """The BVH texts `a` and `b` have the same words in the same places, their numbers within `atol`."""
    x, y = a.split(), b.split()
    assert len(x) == len(y)
    assert all(p == q for p, q in zip(x, y) if not _number(p))
    np.testing.assert_allclose([float(p) for p in x if _number(p)], [float(q) for q in y if _number(q)], atol=atol)


def _number(word: str) -> bool:
    try:
        float(word)
    except ValueError:
        return False
    return True
