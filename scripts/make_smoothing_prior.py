"""Make the per-dof motion scale tables `ptrack/data/cmu_smoothing*.json`: each dof's velocity and
acceleration scale, fitted to real CMU motion.

    python scripts/make_smoothing_prior.py [--clips configs/clips/dev.txt] [--fps 30] \\
        [--out ptrack/data/cmu_smoothing.json]
    python scripts/make_smoothing_prior.py --clips configs/clips/train.txt \\
        --out ptrack/data/cmu_smoothing_train.json

The batch objective's smoothing terms are zero-mean Gaussians on each dof's velocity and acceleration
(`ptrack/estimators/batch/`), and the trackers' dynamics a prior on each dof's velocity
(`kjs.dynamics`); the maximum-likelihood std of such a Gaussian on a clip is the RMS of
the dof's finite-difference velocity (acceleration) there. Per clip (whole AMC at --fps, angle
differences wrapped into [-pi, pi)) the RMS is taken; the scale written is the median over the clips
(one clip with Euler-angle flips of the root, e.g. a pirouette, does not set it), floored at
0.1 rad/s and 1 rad/s^2 for dofs the clips never move (CMU leaves the clavicles at zero). The root
translation gets an acceleration scale only: its velocity is not zero-mean (walking moves on), so
the config's `batch.velocity_sigma_m` stays in force for it.

Two tables ship (`ptrack.body.pose_prior.SMOOTHING_TABLES`): "cmu" (`cmu_smoothing.json`, `batch.prior`'s
default) from the dev clips (`configs/clips/dev.txt`), never the held-out ones
(`configs/clips/heldout_batch.txt`) on which it is checked; "cmu-train" (`cmu_smoothing_train.json`,
`kjs.dynamics`'s default) from `configs/clips/train.txt`, clips of subjects with no dev clip and none
of the held-out clips, so that the trackers' dev and held-out figures are measured on motion it was not
fitted to.
"""

from __future__ import annotations

import argparse
import json
import math
import statistics
import sys
from datetime import date
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from ptrack.body.skeleton import Skeleton, load_amc  # noqa: E402

FLOOR_VELOCITY = 0.1  # rad/s
FLOOR_ACCEL = 1.0  # rad/s^2


def clip_paths(listing: Path) -> list[Path]:
    out = []
    for line in listing.read_text().splitlines():
        line = line.split("#")[0].strip()
        if line:
            out.append((listing.parent / line).resolve())
    return out


def rms_rates(amc: Path, fps: float) -> tuple[list[str], list[bool], np.ndarray, np.ndarray]:
    """dof names, angular flags, per-dof RMS velocity and acceleration of one clip at `fps`."""
    sk = Skeleton.from_asf(amc.parent / f"{amc.stem.split('_')[0]}.asf")
    motion = load_amc(amc, sk)
    stride = max(round(motion.frame_rate / fps), 1)
    q = motion.q.numpy()[::stride]
    dt = stride / motion.frame_rate
    angular = np.asarray(sk.angular_dofs(), dtype=bool)
    d1 = np.diff(q, axis=0)
    d1 = np.where(angular, np.remainder(d1 + math.pi, 2 * math.pi) - math.pi, d1)
    vel, acc = d1 / dt, np.diff(d1, axis=0) / dt**2
    return list(sk.dof_names), list(angular), np.sqrt((vel**2).mean(0)), np.sqrt((acc**2).mean(0))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--clips", type=Path, default=ROOT / "configs" / "clips" / "dev.txt")
    ap.add_argument("--fps", type=float, default=30.0)
    ap.add_argument("--out", type=Path, default=ROOT / "ptrack" / "data" / "cmu_smoothing.json")
    args = ap.parse_args()
    per: dict[str, list[tuple[float, float]]] = {}
    kinds: dict[str, bool] = {}
    names_used = []
    for amc in clip_paths(args.clips):
        names, angular, vel, acc = rms_rates(amc, args.fps)
        names_used.append(amc.stem)
        for n, a, v, c in zip(names, angular, vel, acc):
            per.setdefault(n, []).append((float(v), float(c)))
            kinds[n] = a
    velocity, accel = {}, {}
    for n, vals in per.items():
        v = statistics.median(x[0] for x in vals)
        c = statistics.median(x[1] for x in vals)
        if kinds[n]:
            velocity[n] = round(max(v, FLOOR_VELOCITY), 4)
            accel[n] = round(max(c, FLOOR_ACCEL), 3)
        else:
            accel[n] = round(c, 3)
    doc = {
        "about": "per-dof motion scales (velocity rad/s or m/s, acceleration rad/s^2 or m/s^2) of method: "
        "batch's smoothing prior and the trackers' dynamics: the median over the clips of each clip's RMS "
        "finite-difference rate at fps; made by scripts/make_smoothing_prior.py",
        "made": date.today().isoformat(),
        "fps": args.fps,
        "clips": names_used,
        "velocity": velocity,
        "accel": accel,
    }
    args.out.write_text(json.dumps(doc, indent=1) + "\n")
    print(f"wrote {args.out}: {len(accel)} dofs from {len(names_used)} clips ({', '.join(names_used)})")


if __name__ == "__main__":
    main()
