"""Detector-like footage made from motion capture, with its 3D truth: a COCO-17 results JSON (AlphaPose /
Detectron layout) and an OpenCV YAML camera with intrinsics only, for checking the real-footage path
where the truth is known.

The keypoints are the landmarks of COCO-17 on the clip's own skeleton (`ptrack.body.subject`: the joints a
landmark is placed on, the face on offsets from the head) seen by a camera 5 m away, with Gaussian pixel
noise; the face keypoints (nose, eyes, ears) get score 0 (a detector trained on other faces); a smaller
bystander (the same person shrunk and shifted) is added to some images, and one image has nobody.

    python scripts/synthetic_footage.py AMC OUT_DIR [--frames N] [--noise-px 2] [--seed 0]

writes OUT_DIR/keypoints.json, OUT_DIR/camera.yml and OUT_DIR/truth.npz (keypoints (T, 17, 3) in the camera
frame turned Y-up, as a run without extrinsics reports them; keypoint_names; height_m, the skeleton's
standing height).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import torch

from ptrack.body.keypoint_sets import COCO_17
from ptrack.body.skeleton import Skeleton, load_amc
from ptrack.body.subject import add_landmark_joints, landmark_joints, standing_height
from ptrack.observe.camera import look_at
from ptrack.pipeline.metrics import pa_mpjpe

FACE = ("nose", "l_eye", "r_eye", "l_ear", "r_ear")


def make(
    amc: Path,
    asf: Path,
    out: Path,
    frames: int = 60,
    stride: int = 4,
    noise_px: float = 2.0,
    seed: int = 0,
    width: int = 1280,
    height: int = 720,
    face: bool = False,
) -> dict:
    """Write the footage of `frames` frames (every `stride`-th AMC frame: 30 fps from 120) into `out` (face:
    the face keypoints scored as the rest); -> a summary {height_m, fps, frames, nobody}."""
    rng = np.random.default_rng(seed)
    sk = Skeleton.from_asf(asf)
    h = standing_height(sk)
    sk = add_landmark_joints(sk, h)
    motion = load_amc(amc, sk).slice(0, frames * stride, stride)
    joints = sk.forward_kinematics(motion.q.to(torch.float64))
    placed = landmark_joints(sk, COCO_17.landmarks)
    idx = torch.tensor([sk.joint_index(str(j)) for j in placed])
    pts = joints[:, idx]  # (T, 17, 3)
    centre = joints[:, 0].mean(0)
    cam = look_at(centre, 5.0, 30.0, 5.0, 1000.0, width, height)
    px = cam.project(pts).pixels.numpy()
    T = px.shape[0]
    obs = px + rng.normal(0.0, noise_px, px.shape)
    score = np.ones((T, 17))
    if not face:
        score[:, [COCO_17.landmarks.index(m) for m in FACE]] = 0.0
    nobody = T // 2
    results = []
    for t in range(T):
        if t == nobody:
            continue
        kp = np.concatenate([obs[t], score[t, :, None]], -1)
        kp[score[t] == 0] = 0.0
        results.append({"image_id": t, "category_id": 1, "keypoints": kp.ravel().round(3).tolist(), "score": 0.9})
        if t % 3 == 0:  # a bystander: the person at 60% size, 300 px to the side
            b = (obs[t] - obs[t].mean(0)) * 0.6 + obs[t].mean(0) + np.array([300.0, 40.0])
            bk = np.concatenate([b, np.full((17, 1), 0.8)], -1)
            results.append({"image_id": t, "category_id": 1, "keypoints": bk.ravel().round(3).tolist(), "score": 0.7})
    out.mkdir(parents=True, exist_ok=True)
    (out / "keypoints.json").write_text(json.dumps(results))
    K = cam.K.numpy()
    (out / "camera.yml").write_text(
        "%YAML:1.0\n---\n"
        f"image_width: {width}\nimage_height: {height}\n"
        "camera_matrix: !!opencv-matrix\n   rows: 3\n   cols: 3\n   dt: d\n"
        f"   data: [ {', '.join(f'{v:.6f}' for v in K.ravel())} ]\n"
        "distortion_coefficients: !!opencv-matrix\n   rows: 1\n   cols: 5\n   dt: d\n   data: [ 0., 0., 0., 0., 0. ]\n"
    )
    # the truth in the camera frame turned Y-up (a run's world without extrinsics)
    in_cam = (pts @ cam.R.T.to(pts) + cam.t.to(pts)).numpy() * np.array([1.0, -1.0, -1.0])
    np.savez(
        out / "truth.npz", keypoints=in_cam, keypoint_names=np.asarray(COCO_17.names), height_m=h, frames=np.arange(T)
    )
    return {"height_m": h, "fps": 120.0 / stride, "frames": T, "nobody": nobody}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("amc", type=Path)
    ap.add_argument("out", type=Path)
    ap.add_argument("--asf", type=Path, default=None, help="the skeleton (default: the .asf beside the AMC)")
    ap.add_argument("--frames", type=int, default=60)
    ap.add_argument("--noise-px", type=float, default=2.0)
    ap.add_argument("--seed", type=int, default=0)
    a = ap.parse_args()
    asf = a.asf or next(a.amc.parent.glob("*.asf"))
    print(make(a.amc, asf, a.out, a.frames, noise_px=a.noise_px, seed=a.seed))


def score(result: Path, truth: Path, names: tuple[str, ...] | None = None) -> dict[str, float]:
    """A run's result.npz against truth.npz over the keypoints `names` (default: COCO-17's 12 body points), both in
    the camera's frame turned Y-up (whatever frame the run reported in): {mpjpe_mm (the mid-hip aligned),
    pa_mpjpe_mm, frames}."""
    names = names or COCO_17.names[5:]
    with np.load(result) as r, np.load(truth) as t:
        rn, tn = [str(n) for n in r["keypoint_names"]], [str(n) for n in t["keypoint_names"]]
        # the run's keypoints in the truth's frame, the camera's turned Y-up: world -> model -> camera -> turned
        model = r["keypoints"][:, [rn.index(n) for n in names]] @ r["world_from_model"]
        est = (model @ r["camera_R"].T.astype(np.float64) + r["camera_t"]) * np.array([1.0, -1.0, -1.0])
        ref = t["keypoints"][r["frames"]][:, [tn.index(n) for n in names]]
    hips = [names.index(n) for n in ("left_hip", "right_hip")]
    rel = (est - est[:, hips].mean(1, keepdims=True)) - (ref - ref[:, hips].mean(1, keepdims=True))
    pa = pa_mpjpe(torch.as_tensor(est), torch.as_tensor(ref))
    return {
        "mpjpe_mm": 1000 * float(np.linalg.norm(rel, axis=-1).mean()),
        "pa_mpjpe_mm": float(pa.mean()),
        "frames": len(est),
    }


if __name__ == "__main__":
    main()
