"""Estimators: each turns a `Problem` into an `Estimate`.

`ESTIMATORS` maps a config's `method` name to a function
`(problem, cfg, generator, progress) -> Estimate`, where `cfg` is the whole `RunConfig` (each
method reads its own section), `generator` a seeded `torch.Generator` and `progress` wraps an
iterable to show progress (identity when quiet).

No estimator imports another (tests/test_layers.py): where one starts from another's output (batch from
the per-frame fits), the two are put together here.
"""

from collections.abc import Callable
from functools import partial

from ptrack.estimators import batch
from ptrack.estimators.frame import estimate_frames
from ptrack.estimators.kjs import estimate_css, estimate_kjs, estimate_ss
from ptrack.estimators.pca import estimate_pca
from ptrack.problem import Estimate

#: `batch.estimate_batch`, started (where neither `init_from` nor the keyframes give the start) from the
#: per-frame fits of `estimate_frames`
estimate_batch = partial(batch.estimate_batch, per_frame=estimate_frames)

ESTIMATORS: dict[str, Callable[..., Estimate]] = {
    "frame": estimate_frames,
    "kjs": estimate_kjs,
    "css": estimate_css,
    "ss": estimate_ss,
    "batch": estimate_batch,
    "pca": estimate_pca,
}

__all__ = [
    "ESTIMATORS",
    "estimate_batch",
    "estimate_css",
    "estimate_frames",
    "estimate_kjs",
    "estimate_pca",
    "estimate_ss",
]
