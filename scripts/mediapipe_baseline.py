"""The peer baseline of issue 40: MediaPipe Pose's own 3D (its world landmarks) on the Pose2Sim balancing trial.

For each camera (cam01, cam02 by default), `ptrack.observe.detector.detect` runs MediaPipe Pose
(model_complexity=1) on the trial's video, and its world landmarks (metres, origin between the hips, camera-like
axes: x right, y down, z away) are compared with the 3D reference `balancing/triangulated.trc` (Pose2Sim's
triangulation from four cameras) on the 12 body keypoints: shoulders, elbows, wrists, hips, knees, ankles.

- PA-MPJPE: per frame, the similarity transform (rotation, translation, scale; Umeyama) that best aligns
  MediaPipe's 12 points to the reference's, then the mean distance; averaged over frames, mm.
- root-aligned MPJPE: the reference rotated into the camera's axes (the calibration's R, x_cam = R x_world + t),
  both sets shifted so that their mid-hips coincide, no rotation or scale fitted; averaged over frames, mm.
  MediaPipe's world frame only follows the camera's axes roughly, and its scale is its own guess: this is the
  error a user sees without any alignment but the root.
- two readings of the PA-MPJPE: with MediaPipe's left/right labels exchanged in frames where that fits better
  (how much of the error is side swaps), and the error of holding the reference's first pose still (what no
  detector at all scores on this slow balancing motion).

Frames: the video's frame i is the TRC's frame i + 1 (`OrigDataStartFrame` 0, 60 fps both). The videos decode at
1080 x 1920 while the calibration says 1088 x 1920 (the data's README): no matter here, only 3D is compared.

TRC: OpenSim's layout (header lines, marker names on line 4, X/Y/Z per marker), metres; its axes are the lab's
rotated: TRC (X, Y, Z) = lab (Y, Z, X). The calibration is Pose2Sim's TOML (`[cam_01]`: `rotation` Rodrigues
vector and `translation`, world -> camera).

Usage (from the repo root, with the video extra installed):
    PYTHONPATH=. python scripts/mediapipe_baseline.py [--data ../shared/data/pose2sim] [--cams cam01 cam02]
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

from ptrack.body.keypoint_sets import MEDIAPIPE_33
from ptrack.observe.detector import detect

REPO_ROOT = Path(__file__).resolve().parents[1]
DEFAULT_DATA = REPO_ROOT / ".." / "shared" / "data" / "pose2sim"

#: the 12 body keypoints: (TRC / BODY_25B name, MediaPipe name)
BODY12 = [
    ("LShoulder", "left_shoulder"),
    ("RShoulder", "right_shoulder"),
    ("LElbow", "left_elbow"),
    ("RElbow", "right_elbow"),
    ("LWrist", "left_wrist"),
    ("RWrist", "right_wrist"),
    ("LHip", "left_hip"),
    ("RHip", "right_hip"),
    ("LKnee", "left_knee"),
    ("RKnee", "right_knee"),
    ("LAnkle", "left_ankle"),
    ("RAnkle", "right_ankle"),
]
HIPS = [6, 7]  # LHip, RHip in BODY12
SWAP = [1, 0, 3, 2, 5, 4, 7, 6, 9, 8, 11, 10]  # BODY12 with left and right exchanged


def read_trc(path: Path) -> tuple[np.ndarray, list[str], np.ndarray]:
    """-> (frame numbers (T,) as the TRC counts them, marker names (M,), positions (T, M, 3) in the TRC's axes)."""
    lines = path.read_text().splitlines()
    keys, values = lines[1].split("\t"), lines[2].split("\t")
    header = dict(zip(keys, values))
    names = [n for n in lines[3].split("\t")[2:] if n.strip()]
    if int(header["NumMarkers"]) != len(names):
        raise ValueError(f"{path}: NumMarkers {header['NumMarkers']} but {len(names)} names")
    scale = {"m": 1.0, "mm": 1e-3}[header["Units"]]
    rows = [line.split("\t") for line in lines[5:] if line.strip()]
    data = np.array([[float(x) for x in r[: 2 + 3 * len(names)]] for r in rows])
    return data[:, 0].astype(int), names, data[:, 2:].reshape(len(rows), len(names), 3) * scale


def trc_to_lab(x: np.ndarray) -> np.ndarray:
    """TRC (X, Y, Z) = lab (Y, Z, X)  ->  lab (X, Y, Z) = TRC (Z, X, Y). (..., 3) -> (..., 3)"""
    return x[..., [2, 0, 1]]


def read_calibration(path: Path, cam: str) -> tuple[np.ndarray, np.ndarray]:
    """Pose2Sim's TOML -> (R (3, 3), t (3,)) of `cam` ("cam01" -> section [cam_01]), x_cam = R x_world + t."""
    try:
        import tomllib
    except ImportError:  # Python 3.10
        import tomli as tomllib  # type: ignore[no-redef]
    import cv2

    section = tomllib.loads(path.read_text())[f"cam_{cam[3:]}"]
    R, _ = cv2.Rodrigues(np.asarray(section["rotation"], dtype=float))
    return R, np.asarray(section["translation"], dtype=float)


def procrustes_errors(pred: np.ndarray, ref: np.ndarray) -> np.ndarray:
    """Per-point distances after the similarity transform (Umeyama: rotation, translation, scale) that best
    aligns `pred` to `ref`. (P, 3), (P, 3) -> (P,)"""
    mp, mr = pred.mean(0), ref.mean(0)
    p, r = pred - mp, ref - mr
    U, S, Vt = np.linalg.svd(p.T @ r)
    d = np.sign(np.linalg.det(U @ Vt))
    D = np.diag([1.0, 1.0, d])
    R = (U @ D @ Vt).T  # r ~ s R p
    s = (S * np.diag(D)).sum() / (p**2).sum()
    return np.linalg.norm(s * p @ R.T - r, axis=1)


def evaluate(data: Path, cam: str, stop: int | None) -> dict[str, np.ndarray]:
    """Per-frame errors (mm) of MediaPipe's world landmarks against the TRC for one camera."""
    trc_frames, names, trc = read_trc(data / "balancing" / "triangulated.trc")
    R, _ = read_calibration(data / "Calib_qualisys.toml", cam)
    lm = detect(data / "balancing" / "videos" / f"{cam}.mp4", stop=stop)
    ref_idx = [names.index(n) for n, _ in BODY12]
    mp_idx = [MEDIAPIPE_33.names.index(n) for _, n in BODY12]
    by_frame = {int(f): i for i, f in enumerate(trc_frames)}
    pa, root, per_joint, unswapped, still = [], [], [], [], []
    first = trc_to_lab(trc[by_frame[int(lm.frames[0]) + 1], ref_idx]) if len(lm.frames) else None
    for t, frame in enumerate(lm.frames):
        row = by_frame.get(int(frame) + 1)  # TRC frames count from 1
        pred = lm.world_landmarks[t, mp_idx]
        if row is None or not np.isfinite(pred).all():
            continue
        ref = trc_to_lab(trc[row, ref_idx]) @ R.T  # camera axes (translation irrelevant after root alignment)
        e = procrustes_errors(pred, ref)
        pa.append(e.mean())
        unswapped.append(min(e.mean(), procrustes_errors(pred[SWAP], ref).mean()))
        still.append(procrustes_errors(first, ref).mean())
        per_joint.append(e)
        rooted = (pred - pred[HIPS].mean(0)) - (ref - ref[HIPS].mean(0))
        root.append(np.linalg.norm(rooted, axis=1).mean())
    return {
        "frames": np.asarray(len(lm.frames)),
        "found": np.asarray(int(lm.found.sum())),
        "pa_mpjpe": 1000 * np.asarray(pa),
        "root_mpjpe": 1000 * np.asarray(root),
        "pa_swap_forgiven": 1000 * np.asarray(unswapped),
        "pa_still": 1000 * np.asarray(still),
        "per_joint_pa": 1000 * np.asarray(per_joint),
    }


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--data", type=Path, default=DEFAULT_DATA, help="the pose2sim folder (default ../shared/...)")
    p.add_argument("--cams", nargs="+", default=["cam01", "cam02"])
    p.add_argument("--stop", type=int, default=None, help="only the first STOP frames (a quick look)")
    args = p.parse_args(argv)
    if not (args.data / "balancing" / "triangulated.trc").is_file():
        print(f"no Pose2Sim data at {args.data.resolve()}", file=sys.stderr)
        return 2
    print("MediaPipe Pose (model_complexity=1) world landmarks vs balancing/triangulated.trc, 12 body keypoints")
    for cam in args.cams:
        r = evaluate(args.data, cam, args.stop)
        pa, root = r["pa_mpjpe"], r["root_mpjpe"]
        swapped = int((r["pa_swap_forgiven"] < pa).sum())
        print(f"\n{cam}: a person in {int(r['found'])} of {int(r['frames'])} frames, {len(pa)} compared\n")
        print("| metric (mm) | mean | median | 90th pct |")
        print("|---|---|---|---|")
        rows = (
            ("PA-MPJPE (similarity per frame)", pa),
            ("MPJPE, root (mid-hip) aligned", root),
            (f"PA-MPJPE, left/right swaps forgiven ({swapped} frames)", r["pa_swap_forgiven"]),
            ("PA-MPJPE of no detector: the reference's first pose held", r["pa_still"]),
        )
        for name, v in rows:
            print(f"| {name} | {v.mean():.1f} | {np.median(v):.1f} | {np.percentile(v, 90):.1f} |")
        joints = r["per_joint_pa"].mean(0)
        print("\nPA per keypoint (mm): " + ", ".join(f"{n} {e:.0f}" for (n, _), e in zip(BODY12, joints)))
    return 0


if __name__ == "__main__":
    sys.exit(main())
