"""Make `ptrack/data/cmu_pose_prior.json`: the per-dof Gaussian pose prior of `ptrack.body.pose_prior`.

    python scripts/make_pose_prior.py [--cmu ../shared/data/cmu] [--exclude configs/clips/dev.txt]
                                      [--exclude-clips configs/clips/heldout_batch.txt]
                                      [--stride 4] [--out ptrack/data/cmu_pose_prior.json]

For every non-root dof of the CMU skeleton: the circular mean of the angles in every AMC clip under
`--cmu` whose subject has no clip in `--exclude` (the development clips, so that evaluation on them
is held out) and that is not itself one of `--exclude-clips` (the held-out clips, judged with the prior),
and the root-mean-square angular distance to that mean (each angle's difference is wrapped into [-pi, pi)).
Frames are taken every `--stride` (120 fps -> 30 fps).
"""

from __future__ import annotations

import argparse
import json
import math
from datetime import date
from pathlib import Path

import numpy as np
from make_limits import load_clips

from ptrack.clips import parse_clips

ROOT = Path(__file__).resolve().parents[1]


def circular_stats(q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """q (T, D) radians -> circular mean (D,) and RMS wrapped distance to it (D,)."""
    mean = np.arctan2(np.sin(q).mean(0), np.cos(q).mean(0))
    d = np.angle(np.exp(1j * (q - mean)))
    return mean, np.sqrt((d * d).mean(0))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--cmu", default=str(ROOT / ".." / "shared" / "data" / "cmu"), help="CMU data folder")
    ap.add_argument(
        "--exclude", default=str(ROOT / "configs" / "clips" / "dev.txt"), help="clips file whose subjects are left out"
    )
    ap.add_argument(
        "--exclude-clips",
        default=str(ROOT / "configs" / "clips" / "heldout_batch.txt"),
        help="clips file whose clips (not subjects) are left out",
    )
    ap.add_argument("--stride", type=int, default=4, help="frame stride")
    ap.add_argument("--out", default=str(ROOT / "ptrack" / "data" / "cmu_pose_prior.json"))
    args = ap.parse_args()
    sk, clips = load_clips(Path(args.cmu).resolve())
    held_out = sorted({p.parent.name for p in parse_clips(args.exclude)})
    left_out = sorted(p.stem for p in parse_clips(args.exclude_clips))
    used = {
        name: q[:: args.stride]
        for name, (subject, q) in clips.items()
        if subject not in held_out and name not in left_out
    }
    if not used:
        raise SystemExit("every clip's subject is excluded")
    mean, std = circular_stats(np.concatenate(list(used.values())))
    table = {
        name: [round(math.degrees(mean[i]), 3), round(math.degrees(std[i]), 3)]
        for i, name in enumerate(sk.dof_names)
        if not name.startswith("root.")
    }
    frames = sum(q.shape[0] for q in used.values())
    doc = {
        "description": "Per-dof Gaussian pose prior (degrees): [circular mean, RMS wrapped distance to it] of the "
        "angles in real CMU motion. Root dofs have no prior.",
        "made_by": "scripts/make_pose_prior.py",
        "date": date.today().isoformat(),
        "source": "CMU Graphics Lab Motion Capture Database (mocap.cs.cmu.edu), ASF/AMC, 120 fps",
        "held_out_subjects": held_out,
        "held_out_clips": left_out,
        "clips": sorted(used),
        "stride": args.stride,
        "frames": frames,
        "prior_deg": table,
    }
    Path(args.out).write_text(json.dumps(doc, indent=1) + "\n", encoding="utf-8")
    print(
        f"wrote {args.out}: {len(table)} dofs from {len(used)} clips ({frames} frames), subjects "
        f"{', '.join(held_out)} and clips {', '.join(left_out)} held out"
    )


if __name__ == "__main__":
    main()
