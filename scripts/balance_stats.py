"""How far real people keep their centre of mass from the foot they stand on: `ptrack.body.balance` measured on
the CMU clips (each subject's own skeleton, every 4th frame), per clip and over the clips the priors are fitted
on (less the held-out clips and the synthetic footage's check clips, as `scripts/make_pose_mixture.py`).

Prints per clip the offset of the centre of mass from the support along the body's heading (forward, from the
hips' left-right line) and across it (lateral, to the left), mean and std, and the median and 90th percentile of
the horizontal distance; then the same over the fitting clips. `kjs.balance_sigma_m` is read against these.

Usage (from the repo root):
    PYTHONPATH=. python scripts/balance_stats.py [--cmu ../shared/data/cmu]
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import torch
from eval_synthetic_footage import GROUPS

from ptrack.body.balance import Balance
from ptrack.body.skeleton import Skeleton, load_amc
from ptrack.body.subject import add_landmark_joints, standing_height
from ptrack.clips import parse_clips

ROOT = Path(__file__).resolve().parents[1]


def offsets(asf: Path, amc: Path, stride: int) -> np.ndarray:
    """-> (T, 2) the centre of mass minus the support, (lateral to the left, forward) metres, every stride-th frame."""
    sk = Skeleton.from_asf(asf)
    sk = add_landmark_joints(sk, standing_height(sk))
    joints = sk.forward_kinematics(load_amc(amc, sk).q[::stride].double())
    b = Balance.for_skeleton(sk, 0.1)
    gap = (b.centre_of_mass(joints) - b.support(joints)).numpy()
    left = (joints[:, sk.joint_index("lhipjoint")] - joints[:, sk.joint_index("rhipjoint")]).numpy()
    left[:, 1] = 0.0
    left /= np.linalg.norm(left, axis=1, keepdims=True)
    forward = np.cross(left, [0.0, 1.0, 0.0])  # Y up, X the person's left: forward is left x up
    return np.stack([(gap * left).sum(1), (gap * forward).sum(1)], 1)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--cmu", default=str(ROOT / ".." / "shared" / "data" / "cmu"), help="CMU data folder")
    ap.add_argument("--exclude-clips", default=str(ROOT / "configs" / "clips" / "heldout_batch.txt"))
    ap.add_argument("--stride", type=int, default=4)
    args = ap.parse_args()
    left_out = {p.stem for p in parse_clips(args.exclude_clips)} | set(GROUPS["check"])
    amcs = sorted((Path(args.cmu) / "subjects").glob("*/*.amc"))
    if not amcs:
        raise SystemExit(f"balance_stats: no AMC clips under {Path(args.cmu) / 'subjects'}")
    torch.set_grad_enabled(False)
    fitting = []
    print("| clip | fitting | forward mean / std | lateral mean / std | distance median / 90th pct |")
    print("|---|---|---|---|---|")
    for amc in amcs:
        off = offsets(amc.parent / f"{amc.parent.name}.asf", amc, args.stride)
        d = np.hypot(off[:, 0], off[:, 1])
        fit = amc.stem not in left_out
        if fit:
            fitting.append(off)
        print(
            f"| {amc.stem} | {'yes' if fit else 'no'} | {off[:, 1].mean():+.3f} / {off[:, 1].std():.3f} | "
            f"{off[:, 0].mean():+.3f} / {off[:, 0].std():.3f} | {np.median(d):.3f} / {np.percentile(d, 90):.3f} |"
        )
    a = np.concatenate(fitting)
    d = np.hypot(a[:, 0], a[:, 1])
    print(
        f"\nfitting clips ({len(fitting)}, {len(a)} frames): forward {a[:, 1].mean():+.3f} / {a[:, 1].std():.3f}, "
        f"lateral {a[:, 0].mean():+.3f} / {a[:, 0].std():.3f}, distance median {np.median(d):.3f}, "
        f"90th pct {np.percentile(d, 90):.3f} m"
    )


if __name__ == "__main__":
    main()
