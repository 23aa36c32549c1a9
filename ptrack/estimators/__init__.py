"""Estimators: each turns a `Problem` into an `Estimate`.

`ESTIMATORS` maps a config's `method` name to a function
`(problem, cfg, generator, progress) -> Estimate`, where `cfg` is the whole `RunConfig` (each
method reads its own section), `generator` a seeded `torch.Generator` and `progress` wraps an
iterable to show progress (identity when quiet).
"""

from ptrack.estimators.batch import estimate_batch
from ptrack.estimators.frame import estimate_frames
from ptrack.estimators.kjs import estimate_css, estimate_kjs, estimate_ss
from ptrack.estimators.pca import estimate_pca

ESTIMATORS = {
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
