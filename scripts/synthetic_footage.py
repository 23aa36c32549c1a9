"""Detector-like footage made from motion capture, with its 3D truth: a COCO-17 results JSON (AlphaPose /
Detectron layout) and an OpenCV YAML camera with intrinsics only, for checking the real-footage path
where the truth is known.

The keypoints are the landmarks of COCO-17 on the clip's own skeleton (`ptrack.body.subject`: the joints a
landmark is placed on, the face on offsets from the head) seen by a camera 5 m away, with Gaussian pixel
noise; the face keypoints (nose, eyes, ears, head top) get score 0 (a detector trained on other faces); a
smaller bystander (the same person shrunk and shifted) is added to some images, and one image has nobody.

Two variants come closer to a lab's footage (the Pose2Sim trial: a detector that marks the feet, a calibrated
camera): `--keypoints halpe26` writes HALPE-26 (AlphaPose's set: COCO-17 and the head top, neck, pelvis, big
and little toes and heels; the same results-JSON layout), and `--extrinsics` adds the camera's rotation and
translation (`R`, `T`: the CMU world, Y up) to the YAML and the floor's height to truth.npz (`floor_m`: the
median over the frames of the lowest foot point, less that point's clearance when standing flat), for a run with
`camera.up=y camera.floor_m=<floor_m>`.

    python scripts/synthetic_footage.py AMC OUT_DIR [--frames N] [--noise-px 2] [--seed 0]
        [--keypoints coco17|halpe26] [--extrinsics]

writes OUT_DIR/keypoints.json, OUT_DIR/camera.yml and OUT_DIR/truth.npz (keypoints (T, K, 3) in the camera
frame turned Y-up, as a run without extrinsics reports them, whatever frame the run reports in; keypoint_names;
keypoint_set; height_m, the skeleton's standing height; floor_m with `--extrinsics`).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import torch

from ptrack.body.keypoint_sets import COCO_17, get_keypoint_set
from ptrack.body.skeleton import Skeleton, load_amc
from ptrack.body.subject import add_landmark_joints, floor_points, landmark_joints, standing_height
from ptrack.observe.camera import look_at
from ptrack.pipeline.metrics import pa_mpjpe

FACE = ("nose", "l_eye", "r_eye", "l_ear", "r_ear", "head_top")
#: the 12 body landmarks scored (shoulders, elbows, wrists, hips, knees, ankles), in COCO-17's order
BODY = ("l_shoulder", "r_shoulder", "l_elbow", "r_elbow", "l_wrist", "r_wrist")
BODY += ("l_hip", "r_hip", "l_knee", "r_knee", "l_ankle", "r_ankle")
#: the keypoint sets `make` writes (`--keypoints`)
KEYPOINT_SETS = ("coco17", "halpe26")


def _matrix(name: str, a: np.ndarray, rows: int, cols: int, digits: int = 9) -> str:
    """One OpenCV FileStorage matrix entry, its values with `digits` decimals."""
    data = ", ".join(f"{v:.{digits}f}" for v in np.asarray(a, dtype=np.float64).ravel())
    return f"{name}: !!opencv-matrix\n   rows: {rows}\n   cols: {cols}\n   dt: d\n   data: [ {data} ]\n"


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
    keypoints: str = "coco17",
    extrinsics: bool = False,
    mirrored: tuple[int, int] | None = None,
) -> dict:
    """Write the footage of `frames` frames (every `stride`-th AMC frame: 30 fps from 120) into `out` (face:
    the face keypoints scored as the rest; keypoints: one of `KEYPOINT_SETS`; extrinsics: the camera's R and T in
    the YAML and the floor in truth.npz; mirrored (first, last): the participant's detections in those images written
    with every left and right label exchanged, as a detector that takes the person for one facing the other way);
    -> a summary {height_m, fps, frames, nobody, floor_m (None without extrinsics)}."""
    if keypoints not in KEYPOINT_SETS:
        raise ValueError(f"synthetic_footage: keypoints must be one of {', '.join(KEYPOINT_SETS)}, got {keypoints!r}")
    kps = get_keypoint_set(keypoints)
    n_kp = kps.num_keypoints
    rng = np.random.default_rng(seed)
    sk = Skeleton.from_asf(asf)
    h = standing_height(sk)
    sk = add_landmark_joints(sk, h)
    motion = load_amc(amc, sk).slice(0, frames * stride, stride)
    joints = sk.forward_kinematics(motion.q.to(torch.float64))
    placed = landmark_joints(sk, kps.landmarks)
    on = [i for i, j in enumerate(placed) if j is not None]  # landmarks the skeleton places (all, for these sets)
    pts = joints.new_zeros(joints.shape[0], n_kp, 3)
    pts[:, on] = joints[:, torch.tensor([sk.joint_index(str(placed[i])) for i in on])]  # (T, K, 3)
    centre = joints[:, 0].mean(0)
    cam = look_at(centre, 5.0, 30.0, 5.0, 1000.0, width, height)
    px = cam.project(pts).pixels.numpy()
    T = px.shape[0]
    obs = px + rng.normal(0.0, noise_px, px.shape)
    score = np.zeros((T, n_kp))
    score[:, on] = 1.0
    if not face:
        score[:, [kps.landmarks.index(m) for m in FACE if m in kps.landmarks]] = 0.0
    nobody = T // 2
    results = []
    for t in range(T):
        if t == nobody:
            continue
        kp = np.concatenate([obs[t], score[t, :, None]], -1)
        kp[score[t] == 0] = 0.0
        if mirrored is not None and mirrored[0] <= t <= mirrored[1]:
            kp = kp[kps.mirror_index()]
        results.append({"image_id": t, "category_id": 1, "keypoints": kp.ravel().round(3).tolist(), "score": 0.9})
        if t % 3 == 0:  # a bystander: the person at 60% size, 300 px to the side
            b = (obs[t] - obs[t].mean(0)) * 0.6 + obs[t].mean(0) + np.array([300.0, 40.0])
            bk = np.concatenate([b, np.full((n_kp, 1), 0.8)], -1)
            results.append({"image_id": t, "category_id": 1, "keypoints": bk.ravel().round(3).tolist(), "score": 0.7})
    out.mkdir(parents=True, exist_ok=True)
    (out / "keypoints.json").write_text(json.dumps(results))
    K = cam.K.numpy()
    yml = f"%YAML:1.0\n---\nimage_width: {width}\nimage_height: {height}\n"
    yml += _matrix("camera_matrix", K, 3, 3, digits=6) + _matrix("distortion_coefficients", np.zeros(5), 1, 5, digits=1)
    floor = None
    if extrinsics:  # the CMU world: Y up; the floor where the lowest foot point stands flat
        yml += _matrix("R", cam.R.numpy(), 3, 3) + _matrix("T", cam.t.numpy(), 3, 1)
        feet, clearance = floor_points(sk, h)
        floor = float(joints[:, list(feet), 1].amin(-1).median()) - clearance
    (out / "camera.yml").write_text(yml)
    # the truth in the camera frame turned Y-up (a run's world without extrinsics)
    in_cam = (pts @ cam.R.T.to(pts) + cam.t.to(pts)).numpy() * np.array([1.0, -1.0, -1.0])
    extra = {} if floor is None else {"floor_m": floor}
    np.savez(
        out / "truth.npz",
        keypoints=in_cam,
        keypoint_names=np.asarray(kps.names),
        keypoint_set=np.asarray(keypoints),
        height_m=h,
        frames=np.arange(T),
        **extra,
    )
    return {"height_m": h, "fps": 120.0 / stride, "frames": T, "nobody": nobody, "floor_m": floor}


def body_names(truth: Path) -> tuple[str, ...]:
    """The 12 body points (`BODY`: shoulders, elbows, wrists, hips, knees, ankles) as truth.npz's keypoint set
    names them."""
    with np.load(truth) as t:
        kps = get_keypoint_set(str(t["keypoint_set"])) if "keypoint_set" in t.files else COCO_17
    return tuple(kps.names[kps.landmarks.index(m)] for m in BODY)


def camera_frame_pairs(result: Path, truth: Path, names: tuple[str, ...]) -> tuple[np.ndarray, np.ndarray]:
    """A run's result.npz and truth.npz -> the keypoints `names` of the run's frames, estimated and true, (T, K, 3)
    metres each, in the truth's frame (the camera's, turned Y-up), whatever frame the run reported in."""
    with np.load(result) as r, np.load(truth) as t:
        rn, tn = [str(n) for n in r["keypoint_names"]], [str(n) for n in t["keypoint_names"]]
        # world -> model -> camera -> turned
        model = r["keypoints"][:, [rn.index(n) for n in names]] @ r["world_from_model"]
        est = (model @ r["camera_R"].T.astype(np.float64) + r["camera_t"]) * np.array([1.0, -1.0, -1.0])
        ref = t["keypoints"][r["frames"]][:, [tn.index(n) for n in names]]
    return est, ref


def score(result: Path, truth: Path, names: tuple[str, ...] | None = None) -> dict[str, float]:
    """A run's result.npz against truth.npz over the keypoints `names` (default: the 12 body points, `BODY`, as the
    truth's keypoint set names them), both in the camera's frame turned Y-up (whatever frame the run reported in):
    {mpjpe_mm (the mid-hip aligned), pa_mpjpe_mm, frames}."""
    body = body_names(truth)
    names = names or body
    est, ref = camera_frame_pairs(result, truth, names)
    hips = [names.index(n) for n in body[6:8]]
    rel = (est - est[:, hips].mean(1, keepdims=True)) - (ref - ref[:, hips].mean(1, keepdims=True))
    pa = pa_mpjpe(torch.as_tensor(est), torch.as_tensor(ref))
    return {
        "mpjpe_mm": 1000 * float(np.linalg.norm(rel, axis=-1).mean()),
        "pa_mpjpe_mm": float(pa.mean()),
        "frames": len(est),
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("amc", type=Path)
    ap.add_argument("out", type=Path)
    ap.add_argument("--asf", type=Path, default=None, help="the skeleton (default: the .asf beside the AMC)")
    ap.add_argument("--frames", type=int, default=60)
    ap.add_argument("--noise-px", type=float, default=2.0)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--keypoints", choices=KEYPOINT_SETS, default="coco17")
    ap.add_argument(
        "--extrinsics", action="store_true", help="the camera's R and T in the YAML, the floor in truth.npz"
    )
    ap.add_argument("--mirror", type=image_range, default=None, metavar="A-B", help="images A..B labelled mirrored")
    a = ap.parse_args()
    asf = a.asf or next(a.amc.parent.glob("*.asf"))
    print(
        make(
            a.amc,
            asf,
            a.out,
            a.frames,
            noise_px=a.noise_px,
            seed=a.seed,
            keypoints=a.keypoints,
            extrinsics=a.extrinsics,
            mirrored=a.mirror,
        )
    )


def image_range(text: str) -> tuple[int, int]:
    """'A-B' -> (A, B), for --mirror."""
    try:
        a, b = (int(x) for x in text.split("-"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected A-B (two image numbers), got {text!r}") from None
    if not 0 <= a <= b:
        raise argparse.ArgumentTypeError(f"expected 0 <= A <= B, got {text!r}")
    return a, b


if __name__ == "__main__":
    main()
