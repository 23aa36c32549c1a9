"""A per-dof Gaussian pose prior measured on real CMU motion, for fits that have no 3D input.

A single monocular view leaves every limb's depth and the torso's lean ambiguous: many poses
reproject onto the same 2D joints, and on a start without 3D input (`kjs.init: tree`) the only thing
that ranks them is a prior over poses. An all-zero "rest" prior is a poor one for ASF skeletons,
whose zero pose has the arms straight out sideways: the truth of a walking frame costs more under it
than a wrong interpretation with the arms half raised in depth. This prior holds, for each dof, the
circular mean and the standard deviation (about that mean, on the circle) of the angles real people
take, from `ptrack/data/cmu_pose_prior.json`, made by `scripts/make_pose_prior.py` from CMU clips of
subjects that are not in the development clips (`configs/clips/dev.txt`), less the held-out clips
(`configs/clips/heldout_batch.txt`; since 2026-11-29: four of them had been in it), so that neither split is
judged with a prior fitted to it.

    mean, std, known = pose_prior(skeleton, lower, upper, angular)   # (D,), (D,), (D,) bool

Beside it, the motion's per-dof velocity and acceleration scales (`smoothing_prior(name)`, made by
`scripts/make_smoothing_prior.py`): "cmu" (`ptrack/data/cmu_smoothing.json`, from the dev clips) is the
smoothing prior of `method: batch`; "cmu-train" (`ptrack/data/cmu_smoothing_train.json`, from training
clips of other subjects) the trackers' dynamics (`kjs.dynamics`).
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import TYPE_CHECKING

import torch
from torch import Tensor

from ptrack.body.limits import wrap_to_limits
from ptrack.errors import InputError
from ptrack.package_data import data_file

if TYPE_CHECKING:
    from ptrack.body.skeleton import Skeleton


def pose_prior_path() -> Path:
    """The shipped CMU pose prior file."""
    return data_file("cmu_pose_prior.json")


def read_pose_prior(path: str | Path | None = None) -> dict[str, tuple[float, float]]:
    """{dof name: (mean, std) radians} from a pose prior JSON file.

    Layout: {"prior_deg": {"lfemur.rx": [mean, std], ...}, ...provenance keys}."""
    p = Path(path) if path is not None else pose_prior_path()
    if not p.is_file():
        raise FileNotFoundError(f"pose prior file not found: {p}")
    try:
        table = json.loads(p.read_text(encoding="utf-8"))["prior_deg"]
        items = list(table.items())
    except (json.JSONDecodeError, KeyError, TypeError, AttributeError) as e:
        raise InputError(f"pose prior file {p} must be JSON with a 'prior_deg' mapping ({e})") from None
    out: dict[str, tuple[float, float]] = {}
    for name, v in items:
        if (
            not isinstance(v, list)
            or len(v) != 2
            or not all(isinstance(x, (int, float)) for x in v)
            or not all(math.isfinite(x) for x in v)
            or v[1] < 0
        ):
            raise InputError(f"pose prior file {p}: {name!r} must be [mean, std >= 0] degrees, got {v!r}")
        out[name] = (math.radians(v[0]), math.radians(v[1]))
    return out


def pose_prior(
    sk: Skeleton, lower: Tensor, upper: Tensor, angular: Tensor, path: str | Path | None = None
) -> tuple[Tensor, Tensor, Tensor]:
    """The prior of `sk`'s dofs: -> mean (D,) radians (wrapped into the limits' windows), std (D,),
    known (D,) bool (dofs the file names; the others get mean 0, std 0). dtype and device follow
    `lower`. Root dofs are never in the file (a heading or a position has no prior)."""
    table = read_pose_prior(path)
    mean = torch.zeros_like(lower)
    std = torch.zeros_like(lower)
    known = torch.zeros(lower.shape, dtype=torch.bool, device=lower.device)
    for i, name in enumerate(sk.dof_names):
        if name in table:
            mean[i], std[i] = table[name]
            known[i] = True
    return wrap_to_limits(mean, lower, upper, angular), std, known


def held_sigma(std: Tensor, known: Tensor, floor: float) -> Tensor:
    """The std (D,) an objective holds each dof to its prior mean with: `pose_prior`'s std at least `floor`
    (radians) where the file names the dof, 1e6 (no pull) where it does not. std, known (D,)."""
    return torch.where(known, std.clamp_min(floor), torch.full_like(std, 1e6))


#: the per-dof motion scale tables shipped in ptrack/data, by config name (`batch.prior`, `kjs.dynamics`); both
#: made by `scripts/make_smoothing_prior.py`: "cmu" from the dev clips (configs/clips/dev.txt), "cmu-train"
#: from the training clips (configs/clips/train.txt: subjects with no dev clip, none of the held-out clips)
SMOOTHING_TABLES = {"cmu": "cmu_smoothing.json", "cmu-train": "cmu_smoothing_train.json"}


def check_smoothing_table(name: str | None, key: str) -> None:
    """Raise InputError naming the config key `key` unless `name` is a table of `SMOOTHING_TABLES` or None."""
    if name is not None and name not in SMOOTHING_TABLES:
        raise InputError(f"config key '{key}' must be one of {', '.join(SMOOTHING_TABLES)} or null, got {name!r}")


def smoothing_prior(name: str | None, key: str = "batch.prior") -> dict[str, dict[str, float]]:
    """Per-dof smoothing scales by dof name: {"velocity": {dof: rad/s or m/s}, "accel": {dof: rad/s^2 or
    m/s^2}} from the table `name` of `SMOOTHING_TABLES`; None: none (the config's scalar sigmas for every
    dof). key: the config key named in the error for another name."""
    check_smoothing_table(name, key)
    if name is None:
        return {}
    doc = json.loads(data_file(SMOOTHING_TABLES[name]).read_text(encoding="utf-8"))
    return {"velocity": doc["velocity"], "accel": doc["accel"]}


__all__ = [
    "SMOOTHING_TABLES",
    "check_smoothing_table",
    "pose_prior",
    "pose_prior_path",
    "read_pose_prior",
    "smoothing_prior",
]
