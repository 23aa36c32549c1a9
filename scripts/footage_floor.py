"""How close can a fit of one camera's 2D come to the Pose2Sim trial's 3D reference? A floor for issue 40's
accuracy targets that no search or prior choice is part of.

For each camera (cam01, cam02): the detector's 2D of the balancing trial (OpenPose BODY_25B files, or
`--detections FILE` with `{cam}` in it, e.g. MediaPipe's npz), read as `ptrack run configs/video.yaml` reads
it (the person chosen, the lens distortion removed), and the 12 body keypoints of the four-camera
triangulation (`eval_footage.py`'s reference). Then, started AT the reference, the 3D of the 12 keypoints
(T, 12, 3) is fitted by L-BFGS to

    sum  conf * log(1 + |pixel - detection|^2 / sigma_px^2)        (the robust 2D term, each keypoint free)
  + sum  ((|X_a - X_b| - L_ab) / 0.01 m)^2                          (14 rigid segments: limbs, widths, trunk
                                                                     sides and diagonals)
  + w_acc * sum  (acceleration / 0.005 m per frame^2)^2             (smooth in time; --acc)

with L_ab the reference's own median lengths. The fit keeps every keypoint free (more freedom than ptrack's
skeleton), the lengths exact and the right depth order from the start: what remains is the error that the
one camera's 2D, the rigid lengths and smoothness put there. Printed per camera, mm (MPJPE no alignment /
PA-MPJPE), with `--acc` 1 and 10:

    rigid      the nearest rigid body to the reference (no 2D, no smoothness): the reference's own
               non-rigidity (its segment lengths vary by 3-10%, one std)
    fit        the fit above
    2D         the detector's 2D against the reference reprojected, median px

    PYTHONPATH=. python scripts/footage_floor.py [--cameras cam01,cam02] [--detections FILE] [--sigma-px 8]
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
import torch
from eval_footage import BODY12, DATA, FPS, HEIGHT_M, read_trc

from ptrack.body.keypoint_sets import BODY_25B, get_keypoint_set
from ptrack.body.skeleton import Skeleton
from ptrack.pipeline.config import load_config
from ptrack.pipeline.footage import prepare_footage
from ptrack.pipeline.metrics import pa_mpjpe

REPO = Path(__file__).resolve().parents[1]
SEGMENTS = [
    ("LShoulder", "LElbow"), ("LElbow", "LWrist"), ("RShoulder", "RElbow"), ("RElbow", "RWrist"),
    ("LHip", "LKnee"), ("LKnee", "LAnkle"), ("RHip", "RKnee"), ("RKnee", "RAnkle"),
    ("LShoulder", "RShoulder"), ("LHip", "RHip"), ("LShoulder", "LHip"), ("RShoulder", "RHip"),
    ("LShoulder", "RHip"), ("RShoulder", "LHip"),
]  # fmt: skip
LENGTH_SIGMA_M = 0.01
ACC_SIGMA_M = 0.005


def camera_inputs(cam: str, detections: str | None) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """-> the 12 body keypoints' pixels (T, 12, 2) and confidence (T, 12) of `cam`'s chosen person, lens
    distortion removed, with the camera as world -> pixel: P (3, 4) = K [R | t] in the calibration's world,
    and the input's frame numbers (T,)."""
    path = detections.replace("{cam}", cam) if detections else str(DATA / "balancing" / "pose" / f"{cam}_json")
    cfg = load_config(
        REPO / "configs" / "video.yaml",
        [f"observations.file={path}", f"camera.file={DATA / 'Calib_qualisys.toml'}", f"camera.name={cam}"]
        + [f"subject.height_m={HEIGHT_M}", f"observations.fps={FPS}"],
    )
    template = Skeleton.from_asf(cfg.data.asf)
    _, _, obs, frame = prepare_footage(cfg, template, path)
    ks = get_keypoint_set(frame.keypoint_set)
    names = list(obs.keypoint_names)
    idx = [names.index(ks.names[ks.index(BODY_25B.landmarks[BODY_25B.index(n)])]) for n in BODY12]
    cam_ = obs.camera
    R = cam_.R.double().numpy() @ frame.world_from_model.T  # world -> model -> camera
    P = cam_.K.double().numpy() @ np.concatenate([R, cam_.t.double().numpy()[:, None]], 1)
    return obs.keypoints[:, idx].numpy(), obs.confidence[:, idx].numpy(), P, np.asarray(frame.frames)


def reference(frames: np.ndarray) -> np.ndarray:
    """The triangulated TRC's 12 body keypoints at the input's frames, (T, 12, 3) metres, the calibration's world."""
    names, ref = read_trc(DATA / "balancing" / "triangulated.trc")
    ref = ref[:, [names.index(n) for n in BODY12]][:, :, [2, 0, 1]]  # TRC (X, Y, Z) = lab (Y, Z, X)
    return ref[frames]


def lengths(x: torch.Tensor) -> torch.Tensor:
    """(..., 12, 3) -> (..., 14) the `SEGMENTS`' lengths."""
    a = [BODY12.index(p) for p, _ in SEGMENTS]
    b = [BODY12.index(q) for _, q in SEGMENTS]
    return (x[..., a, :] - x[..., b, :]).norm(dim=-1)


def fit(
    ref: np.ndarray, uv: np.ndarray, conf: np.ndarray, P: np.ndarray, sigma_px: float | None, w_acc: float
) -> np.ndarray:
    """The fit of the module docstring started at ref (T, 12, 3); sigma_px None: no 2D term -> (T, 12, 3)."""
    x0 = torch.tensor(np.ascontiguousarray(ref), dtype=torch.float64)
    x = x0.clone().requires_grad_(True)
    L = lengths(x0).median(0).values
    Pt = torch.tensor(P, dtype=torch.float64)
    uv_t, w = torch.tensor(uv, dtype=torch.float64), torch.tensor(conf, dtype=torch.float64)
    opt = torch.optim.LBFGS(
        [x], max_iter=500, line_search_fn="strong_wolfe", tolerance_grad=1e-9, tolerance_change=1e-13
    )

    def closure() -> torch.Tensor:
        opt.zero_grad()
        f = ((lengths(x) - L) / LENGTH_SIGMA_M).square().sum()
        if sigma_px is not None:
            h = torch.cat([x, torch.ones_like(x[..., :1])], -1) @ Pt.T
            r2 = (h[..., :2] / h[..., 2:] - uv_t).square().sum(-1) / sigma_px**2
            f = f + (w * torch.log1p(r2)).sum()
        if w_acc > 0:
            f = f + w_acc * ((x[2:] - 2 * x[1:-1] + x[:-2]) / ACC_SIGMA_M).square().sum()
        f.backward()
        return f

    last = float("inf")
    for _ in range(20):  # L-BFGS restarts until the energy stops falling (4-8 on this trial)
        value = float(opt.step(closure).detach())
        if value > last - 1e-6 * abs(last):
            break
        last = value
    return x.detach().numpy()


def score(est: np.ndarray, ref: np.ndarray) -> str:
    mpjpe = 1000 * np.linalg.norm(est - ref, axis=-1).mean()
    pa = float(pa_mpjpe(torch.as_tensor(est), torch.as_tensor(ref)).mean())
    return f"{mpjpe:.1f} / {pa:.1f}"


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--cameras", default="cam01,cam02")
    ap.add_argument("--detections", default=None, help="a keypoint file per camera, {cam} in its name")
    ap.add_argument("--sigma-px", type=float, default=8.0)
    args = ap.parse_args()
    if not DATA.is_dir():
        sys.exit(f"footage_floor: no data at {DATA}")
    source = args.detections or "OpenPose"
    print(f"| camera | 2D vs reference, median px | rigid | fit, acc 1 | fit, acc 10 | 2D: {source} |")
    print("|---|---|---|---|---|---|")
    for cam in args.cameras.split(","):
        uv, conf, P, frames = camera_inputs(cam, args.detections)
        ref = reference(frames)
        h = np.concatenate([ref, np.ones_like(ref[..., :1])], -1) @ P.T
        px = np.linalg.norm(h[..., :2] / h[..., 2:] - uv, axis=-1)[conf > 0]
        rigid = fit(ref, uv, conf, P, None, 0.0)
        cells = [score(fit(ref, uv, conf, P, args.sigma_px, acc), ref) for acc in (1.0, 10.0)]
        print(f"| {cam} | {np.median(px):.1f} | {score(rigid, ref)} | {' | '.join(cells)} | |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
