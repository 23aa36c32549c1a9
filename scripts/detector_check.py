"""How a detector's 2D on one camera of the Pose2Sim balancing trial agrees with the four-camera triangulation
reprojected into that camera: the errors that no one-camera reconstruction can undo.

    python scripts/detector_check.py KEYPOINTS --camera cam02 [--trc FILE] [--calib FILE] [--fps 60]

KEYPOINTS is anything `observations.file` reads (an OpenPose folder, the detections.npz that `ptrack detect` or a
run with `observations.video` writes, ...). The person is chosen as a run chooses it, the lens distortion removed
from the detections with the calibration's model, and the TRC (its markers are BODY_25B's keypoints) projected
through the calibration's pinhole; keypoints are matched by landmark, frames by input frame number (TRC row i is
input frame i). Keypoints scored under --min-score are missing, as in a run. Printed:

- each keypoint's median distance to the reference's, pixels;
- the same for keypoints in front of the torso and behind it (the reference's depth against the mean depth of its
  shoulders and hips, 3 cm either way): a detector guesses at the far side of the body;
- the frames whose whole body fits the reference better with every left and right label exchanged (a mirrored
  body: MediaPipe on cam02, frames 42-73), and for each left/right pair the frames where that pair alone does.

docs/notes/footage-history.md has what it found on OpenPose's and MediaPipe's 2D.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
from eval_footage import DATA, FPS, read_trc

from ptrack.body.keypoint_sets import BODY_25B, get_keypoint_set
from ptrack.observe.camera_files import read_camera, undistort_points
from ptrack.observe.keypoint_files import read_keypoints
from ptrack.observe.people import select_person

#: the torso's keypoints (BODY_25B names), whose mean depth splits the near side from the far side
TORSO = ("LShoulder", "RShoulder", "LHip", "RHip")
#: keypoints this far (metres) behind or in front of the torso's mean depth count as far or near
SIDE_M = 0.03


def compare(
    keypoints: str | Path,
    camera: str,
    trc: str | Path = DATA / "balancing" / "triangulated.trc",
    calib: str | Path = DATA / "Calib_qualisys.toml",
    fps: float = FPS,
    min_score: float = 0.3,
) -> dict:
    """The detections of `keypoints` against the TRC reprojected into `camera` (the module docstring) -> {names
    (M,) the matched keypoints' names in the file's set; frames (T,) the input frame numbers compared; error (T, M)
    pixels, NaN where missing; depth (T, M) metres behind the torso's mean depth (the reference's); mirrored (T,)
    bool whole-body exchanges; pairs {"left-right": (T,) bool} single pairs exchanged}."""
    track = select_person(read_keypoints(keypoints, None, None, fps), None)
    definition = get_keypoint_set(track.keypoint_set)
    markers, xyz = read_trc(Path(trc))
    cam = read_camera(calib, camera)
    if cam.R is None:
        raise SystemExit(f"detector_check: {calib} gives {camera} no extrinsics")
    # the markers this keypoint set has, by landmark
    matched = [
        (m, definition.landmarks.index(BODY_25B.landmarks[BODY_25B.index(m)]))
        for m in markers
        if m in BODY_25B.names and BODY_25B.landmarks[BODY_25B.index(m)] in definition.landmarks
    ]
    if len(matched) < 2:
        raise SystemExit(f"detector_check: {keypoints} ({definition.name}) shares fewer than 2 keypoints with {trc}")
    names = [definition.names[k] for _, k in matched]
    keep = track.present & (track.frames < len(xyz))
    frames = track.frames[keep]
    ref = xyz[frames][:, [markers.index(m) for m, _ in matched]][..., [2, 0, 1]]  # TRC (X, Y, Z) = lab (Y, Z, X)
    torso = xyz[frames][:, [markers.index(m) for m in TORSO]][..., [2, 0, 1]]
    in_cam = ref @ cam.R.T + cam.t  # (T, M, 3)
    ref_px = in_cam[..., :2] / in_cam[..., 2:] @ cam.K[:2, :2].T + cam.K[:2, 2]
    depth = in_cam[..., 2] - (torso @ cam.R.T + cam.t)[..., 2].mean(-1, keepdims=True)
    pts = track.points[keep][:, [k for _, k in matched]].astype(np.float64)
    seen = (np.nan_to_num(track.scores[keep][:, [k for _, k in matched]]) >= min_score) & np.isfinite(pts).all(-1)
    pts[seen] = undistort_points(pts[seen], cam)
    pts[~seen] = np.nan
    error = np.linalg.norm(pts - ref_px, axis=-1)
    # each matched keypoint's left/right partner among the matched ones (itself when it has none)
    mirror = definition.mirror_index()
    column = {k: i for i, (_, k) in enumerate(matched)}
    partner = np.array([column.get(int(mirror[k]), i) for i, (_, k) in enumerate(matched)])
    paired = partner != np.arange(len(partner))
    exchanged = np.linalg.norm(pts[:, partner] - ref_px, axis=-1)
    both = seen & seen[:, partner] & paired
    count = both.sum(-1)
    own = np.where(both, error, 0.0).sum(-1) / np.maximum(count, 1)
    other = np.where(both, exchanged, 0.0).sum(-1) / np.maximum(count, 1)
    pairs = {}
    for i in np.flatnonzero(paired & (partner > np.arange(len(partner)))):
        j = partner[i]
        ok = seen[:, i] & seen[:, j]
        pairs[f"{names[i]}-{names[j]}"] = ok & (exchanged[:, i] + exchanged[:, j] < error[:, i] + error[:, j])
    return {
        "names": names,
        "frames": frames,
        "error": error,
        "depth": depth,
        "mirrored": (count > 0) & (other < own),
        "pairs": pairs,
    }


def _median(x: np.ndarray) -> float:
    x = x[np.isfinite(x)]
    return float(np.median(x)) if len(x) else float("nan")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("keypoints")
    ap.add_argument("--camera", required=True, help="the calibration's camera name (cam01, cam02)")
    ap.add_argument("--trc", default=str(DATA / "balancing" / "triangulated.trc"))
    ap.add_argument("--calib", default=str(DATA / "Calib_qualisys.toml"))
    ap.add_argument("--fps", type=float, default=FPS)
    ap.add_argument("--min-score", type=float, default=0.3)
    args = ap.parse_args()
    c = compare(args.keypoints, args.camera, args.trc, args.calib, args.fps, args.min_score)
    err, depth = c["error"], c["depth"]
    print(f"{args.keypoints} against {args.trc} reprojected into {args.camera}: {len(c['frames'])} frames")
    print(f"\nmedian 2D error {_median(err):.1f} px; in front of the torso {_median(err[depth < -SIDE_M]):.1f}, level")
    level = np.abs(depth) <= SIDE_M
    print(f"with it {_median(err[level]):.1f}, behind it {_median(err[depth > SIDE_M]):.1f}\n")
    print("| keypoint | median px | frames seen |")
    print("|---|---|---|")
    for i, n in enumerate(c["names"]):
        print(f"| {n} | {_median(err[:, i]):.1f} | {int(np.isfinite(err[:, i]).sum())} |")
    mirrored = c["frames"][c["mirrored"]].tolist()
    print(f"\nwhole body mirrored (every left/right label exchanged) in {len(mirrored)} frames: {mirrored}")
    for pair, flags in c["pairs"].items():
        print(f"{pair} exchanged in {int(flags.sum())} frames")


if __name__ == "__main__":
    main()
