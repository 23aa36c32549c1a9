"""Estimators: each turns a `Problem` into an `Estimate`.

`ESTIMATORS` maps a config's `method` name to a function
`(problem, cfg, generator, progress) -> Estimate`, where `cfg` is the whole `RunConfig` (each
method reads its own section), `generator` a seeded `torch.Generator` and `progress` wraps an
iterable to show progress (identity when quiet).

No estimator imports another (tests/test_layers.py): where one starts from another's output (batch from
the per-frame fits or the kjs tracker; pca hands them the frames after the swing), the two are put together here.
"""

import dataclasses
from collections.abc import Callable, Iterable
from functools import partial

import torch
from torch import Tensor

from ptrack.estimators import batch, pca
from ptrack.estimators.frame import estimate_frames, frames_after
from ptrack.estimators.kjs import estimate_css, estimate_kjs, estimate_ss
from ptrack.problem import Estimate, Keyframes, Problem

#: `batch.estimate_batch`, started (where neither `init_from` nor the keyframes give the start) from the
#: per-frame fits of `estimate_frames`, or with `batch.init: kjs` from the kjs tracker's best trajectory
estimate_batch = partial(batch.estimate_batch, per_frame=estimate_frames, tracker=estimate_kjs)


def batch_after(problem: Problem, cfg, q_before: Tensor, progress: Callable[[Iterable], Iterable]) -> Estimate:
    """The MAP trajectory of `problem` continuing a pose q_before (D,) of the frame before its first: q_before is
    its frame 0's keyframe (the `keyframes:` section's prior stds), which also starts the per-frame fits it
    starts from. No uncertainty (the run reports none for a pca run), one pose per observed frame, no
    `init_from` (a whole run's trajectory, not these frames'); q_before is its only keyframe (pca reads no 3D
    keyframe, nor does what it hands on). Deterministic."""
    kf = Keyframes(torch.zeros(1, dtype=torch.long, device=q_before.device), q_before.detach()[None])
    tail = dataclasses.replace(problem, keyframes=kf, joint_keyframes=None)
    batch_cfg = dataclasses.replace(cfg.batch, uncertainty=False, init="frame", upsample=1)
    quiet = dataclasses.replace(cfg, batch=batch_cfg, init_from=None)
    run = dataclasses.replace(quiet, frame=dataclasses.replace(cfg.frame, init="keyframe"))
    return estimate_batch(tail, run, torch.Generator(device=q_before.device), progress)


#: `pca.estimate_pca`, handing the frames after the swing (`pca.after_swing`) on from the swing's last pose:
#: `batch` (`batch_after`) or `frame` (the per-frame fits `frames_after`)
estimate_pca = partial(pca.estimate_pca, after={"batch": batch_after, "frame": frames_after})

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
