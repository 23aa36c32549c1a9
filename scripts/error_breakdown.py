"""Where a real-footage run's error is: its 12 body keypoints against a 3D reference, broken down.

For each run folder (result.npz and metrics.json of `ptrack run configs/video.yaml`):

    PA-MPJPE        per-frame similarity onto the reference, mean keypoint distance, mm
    MPJPE           no alignment (the reference's frame), mm
    mid-hip offset  the estimated mid-hip minus the reference's, mean vector and mean length, and its mean along
                    the run camera's viewing direction (+: too far), mm
    hip-aligned     the keypoints with the two mid-hips put together (no rotation), mm: with the offset, how much of
                    the MPJPE is the body's position and how much its orientation and shape
    tilt            how far the trunk (mid-hip to mid-shoulder) and the legs (mid-hip to mid-ankle) lean along the
                    viewing direction, the estimate's minus the reference's, degrees (+: the far end away from the
                    camera): the lean that one view hardly sees
    per keypoint    the PA-aligned distance (mm) and its mean signed vector (a bias that the seeds share points at
                    the 2D or the model, not the sampler)
    segments        keypoint-to-keypoint lengths, estimated and reference (means over the frames), and their ratio

The reference: a Pose2Sim run (`scripts/eval_footage.py`'s folders) against the trial's triangulated TRC (the lab's
axes, `--trc` for another); a synthetic run (`scripts/eval_synthetic_footage.py`'s folders OUT/<clip>/<setting>)
against the footage's truth.npz beside it (the camera's frame turned Y-up, `--truth` for another). With several
runs, `--mean` prints the mean over them instead of one block each (e.g. the seeds of one setting).

    python scripts/error_breakdown.py RUN [RUN ...] [--mean] [--trc FILE | --truth FILE]
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))  # the sibling scripts' loaders
import eval_footage
import synthetic_footage

from ptrack.pipeline.metrics import procrustes_align

#: the 12 body keypoints in the order both references give them (synthetic_footage.BODY has the same order)
NAMES = tuple(eval_footage.BODY12)
#: keypoint-to-keypoint lengths: name -> (a, b), each the indices into NAMES of the keypoints averaged for that end
SEGMENTS = {
    "shoulders": ((0,), (1,)),
    "hips": ((6,), (7,)),
    "trunk (mid-hip to mid-shoulder)": ((6, 7), (0, 1)),
    "L upper arm": ((0,), (2,)),
    "R upper arm": ((1,), (3,)),
    "L forearm": ((2,), (4,)),
    "R forearm": ((3,), (5,)),
    "L thigh": ((6,), (8,)),
    "R thigh": ((7,), (9,)),
    "L shank": ((8,), (10,)),
    "R shank": ((9,), (11,)),
}


def pairs(run: Path, trc: Path | None, truth: Path | None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A run folder -> estimated and reference body keypoints (T, 12, 3) metres, in NAMES' order, and the run
    camera's viewing direction (3,) in their frame."""
    result = run / "result.npz"
    if not result.is_file():
        raise SystemExit(f"error_breakdown: no result.npz in {run}")
    beside = run.parent / "footage" / "truth.npz"
    truth = truth or (beside if beside.is_file() else None)
    if truth is not None:  # the camera's frame turned Y-up: it looks along -Z
        est, ref = synthetic_footage.camera_frame_pairs(result, truth, synthetic_footage.body_names(truth))
        return est, ref, np.array([0.0, 0.0, -1.0])
    est, ref = eval_footage.body_pairs(result, trc or eval_footage.DATA / "balancing" / "triangulated.trc")
    with np.load(result) as z:  # the world is world_from_model W times the model frame; the camera's +Z is R's row 2
        view = z["world_from_model"] @ z["camera_R"][2]
    return est, ref, view / np.linalg.norm(view)


def _tilt_deg(v: np.ndarray, view: np.ndarray) -> np.ndarray:
    """How far vectors v (T, 3) point along the viewing direction (away from the camera), degrees (T,)."""
    return np.degrees(np.arcsin(np.clip(v @ view / np.linalg.norm(v, axis=-1), -1.0, 1.0)))


def breakdown(est: np.ndarray, ref: np.ndarray, view: np.ndarray) -> dict[str, np.ndarray | float]:
    """(T, 12, 3) estimated and reference keypoints (metres) and the camera's viewing direction (3,) -> the figures
    of the module docstring (mm, degrees)."""
    aligned = procrustes_align(torch.as_tensor(est), torch.as_tensor(ref)).numpy()
    pa = aligned - ref
    mid_e, mid_r = est[:, 6:8].mean(1, keepdims=True), ref[:, 6:8].mean(1, keepdims=True)
    offset = (mid_e - mid_r)[:, 0]
    length = lambda x, a, b: np.linalg.norm(x[:, list(a)].mean(1) - x[:, list(b)].mean(1), axis=-1).mean()  # noqa: E731

    def tilt(a: slice) -> float:  # the mid-hip -> mid-(a) direction's tilt along the ray, estimate minus reference
        return float(
            (_tilt_deg(est[:, a].mean(1) - mid_e[:, 0], view) - _tilt_deg(ref[:, a].mean(1) - mid_r[:, 0], view)).mean()
        )

    return {
        "pa": 1000 * np.linalg.norm(pa, axis=-1).mean(),
        "mpjpe": 1000 * np.linalg.norm(est - ref, axis=-1).mean(),
        "offset": 1000 * offset.mean(0),
        "offset_length": 1000 * np.linalg.norm(offset, axis=-1).mean(),
        "depth": 1000 * float((offset @ view).mean()),
        "trunk_tilt": tilt(slice(0, 2)),
        "legs_tilt": tilt(slice(10, 12)),
        "hip_aligned": 1000 * np.linalg.norm((est - mid_e) - (ref - mid_r), axis=-1).mean(),
        "keypoint": 1000 * np.linalg.norm(pa, axis=-1).mean(0),
        "bias": 1000 * pa.mean(0),
        "est_lengths": np.array([length(est, a, b) for a, b in SEGMENTS.values()]),
        "ref_lengths": np.array([length(ref, a, b) for a, b in SEGMENTS.values()]),
    }


def report(title: str, b: dict) -> str:
    vec = lambda v: "(" + ", ".join(f"{x:+.0f}" for x in v) + ")"  # noqa: E731
    lines = [f"{title}", ""]
    lines.append(
        f"PA-MPJPE {b['pa']:.1f} mm, MPJPE {b['mpjpe']:.1f} mm, mid-hip offset {vec(b['offset'])} "
        f"(mean length {b['offset_length']:.0f}; along the camera's ray {b['depth']:+.0f}) mm, hip-aligned "
        f"{b['hip_aligned']:.1f} mm; tilt along the ray (away from the camera +), estimate minus reference: trunk "
        f"{b['trunk_tilt']:+.1f} deg, legs {b['legs_tilt']:+.1f} deg"
    )
    lines += ["", "| keypoint | PA error mm | mean signed PA error mm |", "|---|---|---|"]
    lines += [f"| {n} | {e:.0f} | {vec(v)} |" for n, e, v in zip(NAMES, b["keypoint"], b["bias"])]
    lines += ["", "| segment | estimated m | reference m | ratio |", "|---|---|---|---|"]
    for n, e, r in zip(SEGMENTS, b["est_lengths"], b["ref_lengths"]):
        lines.append(f"| {n} | {e:.3f} | {r:.3f} | {e / r:.3f} |")
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("runs", nargs="+", type=Path)
    ap.add_argument("--mean", action="store_true", help="the mean over the runs instead of one block each")
    ref = ap.add_mutually_exclusive_group()
    ref.add_argument("--trc", type=Path, help="a Pose2Sim run's reference (default: the balancing trial's)")
    ref.add_argument("--truth", type=Path, help="a synthetic run's truth.npz (default: ../footage/truth.npz)")
    args = ap.parse_args(argv)
    blocks = [(run, breakdown(*pairs(run, args.trc, args.truth))) for run in args.runs]
    if args.mean:
        mean = {k: np.mean([b[k] for _, b in blocks], axis=0) for k in blocks[0][1]}
        print(report(f"mean of {len(blocks)} runs: {', '.join(str(r) for r, _ in blocks)}", mean))
    else:
        for run, b in blocks:
            print(report(str(run), b))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
