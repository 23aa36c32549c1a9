"""Writes formats/: the shipped OpenPose frames (two_people_cam01/) in the other keypoint containers ptrack reads,
and cameras 1 and 2 of the Pose2Sim calibration (../shared/data/pose2sim/Calib_qualisys.toml) as OpenCV and
EasyMocap files, so that the README's Python guide reads every format on a plain clone. Run from the repository
root: python tests/data/keypoints/make_formats.py (tests/test_readme.py checks that each reads back the same)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from ptrack import read_camera, read_keypoints

HERE = Path(__file__).resolve().parent
OUT = HERE / "formats"
CALIB = HERE.parents[2] / ".." / "shared" / "data" / "pose2sim" / "Calib_qualisys.toml"


def _triplets(kp: np.ndarray) -> list[float]:
    """(K, 3) with NaN for missing points -> the flat [x, y, score] list of the JSON formats (0, 0, 0 when missing)."""
    return np.round(np.nan_to_num(kp), 3).ravel().tolist()


def _matrix(key: str, value: np.ndarray) -> str:
    """One matrix as cv::FileStorage writes it."""
    value = np.atleast_2d(value)
    data = ", ".join(repr(float(v)) for v in value.ravel())
    rows, cols = value.shape
    return f"{key}: !!opencv-matrix\n   rows: {rows}\n   cols: {cols}\n   dt: d\n   data: [ {data} ]\n"


def main() -> None:
    OUT.mkdir(exist_ok=True)
    det = read_keypoints(HERE / "two_people_cam01")
    people = [[p for p in frame if np.isfinite(p[:, :2]).any()] for frame in det.people]  # (T,) lists of (K, 3)

    coco = [
        {"image_id": int(f), "category_id": 1, "keypoints": _triplets(p), "score": 1.0}
        for f, frame in zip(det.frames, people)
        for p in frame
    ]
    (OUT / "two_people_cam01.alphapose.json").write_text(json.dumps(coco) + "\n", encoding="utf-8")

    mmpose = {
        "instance_info": [
            {
                "frame_id": int(f),
                "instances": [
                    {
                        "keypoints": np.round(np.nan_to_num(p[:, :2]), 3).tolist(),
                        "keypoint_scores": np.round(p[:, 2], 3).tolist(),
                    }
                    for p in frame
                ],
            }
            for f, frame in zip(det.frames, people)
        ]
    }
    (OUT / "two_people_cam01.mmpose.json").write_text(json.dumps(mmpose) + "\n", encoding="utf-8")

    np.savez_compressed(OUT / "two_people_cam01.npz", keypoints=det.people.astype(np.float32), frames=det.frames)

    cams = [read_camera(CALIB, n) for n in ("cam01", "cam02")]
    c = cams[0]
    opencv = "%YAML:1.0\n---\n" + f"image_width: {c.width}\nimage_height: {c.height}\n"
    opencv += _matrix("camera_matrix", c.K) + _matrix("distortion_coefficients", c.dist[:, None])
    opencv += _matrix("rvec", Rotation.from_matrix(c.R).as_rotvec()[:, None]) + _matrix("tvec", c.t[:, None])
    (OUT / "cam01.yml").write_text(opencv, encoding="utf-8")

    easy = OUT / "easymocap"
    easy.mkdir(exist_ok=True)
    names = ["01", "02"]
    header = "%YAML:1.0\n---\nnames:\n" + "".join(f'  - "{n}"\n' for n in names)
    intri, extri = header, header
    for n, c in zip(names, cams):
        intri += _matrix(f"K_{n}", c.K) + _matrix(f"dist_{n}", c.dist[None]) + f"H_{n}: {c.height}\nW_{n}: {c.width}\n"
        extri += _matrix(f"R_{n}", Rotation.from_matrix(c.R).as_rotvec()[:, None]) + _matrix(f"Rot_{n}", c.R)
        extri += _matrix(f"T_{n}", c.t[:, None])
    (easy / "intri.yml").write_text(intri, encoding="utf-8")
    (easy / "extri.yml").write_text(extri, encoding="utf-8")


if __name__ == "__main__":
    main()
