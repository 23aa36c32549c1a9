"""Make `ptrack/data/cmu_limits.json`: per-dof joint limits that real CMU motion obeys.

    python scripts/make_limits.py [--cmu ../shared/data/cmu] [--margin-deg 10] [--out ptrack/data/cmu_limits.json]

For every non-root dof of the CMU skeleton, the bounds are the smallest arc of the circle holding
every value that dof takes in every AMC clip under `--cmu` (each clip read with its own subject's
ASF), widened by `--margin-deg` on both sides; an arc that then covers the whole circle is written
as null (unlimited). Angles are periodic, so the arc, not the min/max of the raw AMC numbers,
is the right summary (CMU files contain both 359 and -1 degrees for the same dof).

It also prints the leave-one-subject-out check that chose the margin: limits made without a
subject's clips, and the share of that subject's limited dof-frames outside them, per clip, for
the dofs that the default reduced model estimates (fingers, thumbs, hands, toes frozen).
"""

from __future__ import annotations

import argparse
import json
import math
from datetime import date
from pathlib import Path

import numpy as np
import torch

from ptrack.body.limits import arc_bounds, outside_limits
from ptrack.body.skeleton import Skeleton, load_amc
from ptrack.pipeline.config import ModelConfig

ROOT = Path(__file__).resolve().parents[1]


def load_clips(cmu: Path) -> tuple[Skeleton, dict[str, tuple[str, np.ndarray]]]:
    """Every AMC under cmu/subjects: {clip: (subject, q (T, D) radians)} and one skeleton (the dof
    layout, identical across CMU subjects; checked)."""
    clips: dict[str, tuple[str, np.ndarray]] = {}
    ref = None
    for amc in sorted((cmu / "subjects").glob("*/*.amc")):
        subject = amc.parent.name
        sk = Skeleton.from_asf(amc.parent / f"{subject}.asf")
        if ref is None:
            ref = sk
        elif sk.dof_names != ref.dof_names:
            raise SystemExit(f"{amc}: skeleton dofs differ from the other subjects'")
        clips[amc.stem] = (subject, load_amc(amc, sk).q.numpy())
    if ref is None:
        raise SystemExit(f"no AMC clips under {cmu / 'subjects'}")
    return ref, clips


def bounds_from(qs: list[np.ndarray], sk: Skeleton, margin: float) -> tuple[np.ndarray, np.ndarray]:
    """(D,) lower, upper radians from the clips `qs`; root dofs stay unlimited."""
    q = np.concatenate(qs)
    lower = np.full(sk.num_dofs, -math.inf)
    upper = np.full(sk.num_dofs, math.inf)
    for i, name in enumerate(sk.dof_names):
        if not name.startswith("root."):
            lower[i], upper[i] = arc_bounds(q[:, i], margin)
    return lower, upper


def held_out_rates(sk: Skeleton, clips: dict, margin: float) -> dict[str, float]:
    """{clip: share of its limited estimated dof-frames outside limits made without its subject}."""
    reduced = sk.freeze(list(ModelConfig().freeze))
    keep = [sk.dof_names.index(n) for n in reduced.dof_names]
    angular = torch.as_tensor(sk.angular_dofs())[keep]
    rates = {}
    for subject in sorted({s for s, _ in clips.values()}):
        lower, upper = bounds_from([q for s, q in clips.values() if s != subject], sk, margin)
        lo, hi = torch.as_tensor(lower[keep]), torch.as_tensor(upper[keep])
        limited = torch.isfinite(lo) | torch.isfinite(hi)
        for name, (s, q) in clips.items():
            if s == subject:
                out = outside_limits(torch.as_tensor(q[:, keep]), lo, hi, angular)[:, limited]
                rates[name] = float((out > 1e-3).double().mean())
    return rates


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--cmu", default=str(ROOT / ".." / "shared" / "data" / "cmu"), help="CMU data folder")
    ap.add_argument("--margin-deg", type=float, default=10.0, help="widening of each arc, degrees")
    ap.add_argument("--out", default=str(ROOT / "ptrack" / "data" / "cmu_limits.json"))
    args = ap.parse_args()
    cmu = Path(args.cmu).resolve()
    margin = math.radians(args.margin_deg)
    sk, clips = load_clips(cmu)

    print(
        f"leave-one-subject-out check, margin {args.margin_deg:g} deg "
        "(share of limited dof-frames outside limits made without the clip's subject):"
    )
    rates = held_out_rates(sk, clips, margin)
    for name, r in rates.items():
        print(f"  {name:8s} {100 * r:6.2f}%")
    vals = np.array(list(rates.values()))
    print(
        f"  mean {100 * vals.mean():.2f}%, median {100 * np.median(vals):.2f}%, max {100 * vals.max():.2f}%, "
        f"clips over 0.5%: {int((vals > 0.005).sum())} of {len(vals)}"
    )

    lower, upper = bounds_from([q for _, q in clips.values()], sk, margin)
    table = {}
    for i, name in enumerate(sk.dof_names):
        if name.startswith("root."):
            continue
        table[name] = (
            None
            if not math.isfinite(lower[i])
            else [round(math.degrees(lower[i]), 3), round(math.degrees(upper[i]), 3)]
        )
    frames = sum(q.shape[0] for _, q in clips.values())
    doc = {
        "description": "Per-dof joint limits (degrees) that real CMU motion obeys: the smallest arc holding every "
        "captured value of the dof, widened by margin_deg on each side; null = unlimited "
        "(the widened arc covers the whole circle). Angles are periodic: a value is inside when "
        "some 360-degree shift of it is. Root dofs are not limited.",
        "made_by": "scripts/make_limits.py",
        "date": date.today().isoformat(),
        "margin_deg": args.margin_deg,
        "source": "CMU Graphics Lab Motion Capture Database (mocap.cs.cmu.edu), ASF/AMC, 120 fps",
        "clips": sorted(clips),
        "frames": frames,
        "held_out_violation": {
            "mean": round(float(vals.mean()), 5),
            "max": round(float(vals.max()), 5),
            "per_clip": {k: round(v, 5) for k, v in rates.items()},
        },
        "limits_deg": table,
    }
    Path(args.out).write_text(json.dumps(doc, indent=1) + "\n", encoding="utf-8")
    print(f"wrote {args.out}: {len(table)} dofs from {len(clips)} clips, {frames} frames")


if __name__ == "__main__":
    main()
