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
  + w_acc * sum  (acceleration / 0.005 m per frame^2)^2             (smooth in time, w_acc 1 or 10)

with L_ab the reference's own median lengths. The fit keeps every keypoint free (more freedom than ptrack's
skeleton), the lengths exact and the right depth order from the start: what remains is the error that the
one camera's 2D, the rigid lengths and smoothness put there. Printed per camera, mm (MPJPE no alignment / PA-MPJPE):

    2D              the detector's 2D against the reference reprojected, median px
    rigid           the nearest rigid body to the reference (no 2D, no smoothness): the reference's own
                    non-rigidity (its segment lengths vary by 3-10%, one std)
    fit, acc 1/10   the fit above, smoothness weight 1 and 10
    model fit       ptrack's own skeleton (configs/video.yaml's, with the reference's segment lengths) fitted to
                    the reference in 3D: how close the model can come to it (`model_floor`)
    model polished  that fit, each frame then polished on the camera's 2D by the kjs tracker's frame objective
                    (robust reprojection, limits, collision, the floor; no dynamics): where ptrack's own
                    objective moves a start at the reference

    PYTHONPATH=. python scripts/footage_floor.py [--cameras cam01,cam02] [--detections FILE] [--sigma-px 8]
"""

from __future__ import annotations

import argparse
import sys
import tempfile
from pathlib import Path

import numpy as np
import torch
from eval_footage import BODY12, DATA, FPS, HEIGHT_M, body_rows, reference_body

from ptrack.body.skeleton import Skeleton
from ptrack.estimators.kjs.model import KJS, make_setup, polish
from ptrack.optim.jacobians import joint_jacobian
from ptrack.optim.solvers import levenberg_marquardt
from ptrack.pipeline.config import RunConfig, load_config
from ptrack.pipeline.footage import prepare_footage
from ptrack.pipeline.metrics import pa_mpjpe
from ptrack.pipeline.run import prepare_real, with_segments

REPO = Path(__file__).resolve().parents[1]
SEGMENTS = [
    ("LShoulder", "LElbow"), ("LElbow", "LWrist"), ("RShoulder", "RElbow"), ("RElbow", "RWrist"),
    ("LHip", "LKnee"), ("LKnee", "LAnkle"), ("RHip", "RKnee"), ("RKnee", "RAnkle"),
    ("LShoulder", "RShoulder"), ("LHip", "RHip"), ("LShoulder", "LHip"), ("RShoulder", "RHip"),
    ("LShoulder", "RHip"), ("RShoulder", "LHip"),
]  # fmt: skip
LENGTH_SIGMA_M = 0.01
ACC_SIGMA_M = 0.005


def config(cam: str, detections: str | None, overrides: tuple[str, ...] = ()) -> tuple[RunConfig, str]:
    """configs/video.yaml on `cam`'s detections (OpenPose's folder, or `detections` with `{cam}` in it) ->
    (the config, the keypoint path)."""
    path = detections.replace("{cam}", cam) if detections else str(DATA / "balancing" / "pose" / f"{cam}_json")
    cfg = load_config(
        REPO / "configs" / "video.yaml",
        [f"observations.file={path}", f"camera.file={DATA / 'Calib_qualisys.toml'}", f"camera.name={cam}"]
        + [f"subject.height_m={HEIGHT_M}", f"observations.fps={FPS}", "progress=false", *overrides],
    )
    return cfg, path


def camera_inputs(cam: str, detections: str | None) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """-> the 12 body keypoints' pixels (T, 12, 2) and confidence (T, 12) of `cam`'s chosen person, lens
    distortion removed, with the camera as world -> pixel: P (3, 4) = K [R | t] in the calibration's world,
    and the input's frame numbers (T,)."""
    cfg, path = config(cam, detections)
    template = Skeleton.from_asf(cfg.data.asf)
    _, _, obs, frame = prepare_footage(cfg, template, path)
    idx = body_rows(frame.keypoint_set, list(obs.keypoint_names))
    cam_ = obs.camera
    R = cam_.R.double().numpy() @ frame.world_from_model.T  # world -> model -> camera
    P = cam_.K.double().numpy() @ np.concatenate([R, cam_.t.double().numpy()[:, None]], 1)
    return obs.keypoints[:, idx].numpy(), obs.confidence[:, idx].numpy(), P, np.asarray(frame.frames)


def reference(frames: np.ndarray) -> np.ndarray:
    """The triangulated TRC's 12 body keypoints at the input's frames, (T, 12, 3) metres, the calibration's world."""
    return reference_body(DATA / "balancing" / "triangulated.trc", frames)


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


def reference_segments(ref: np.ndarray) -> dict[str, dict]:
    """The reference's own segment lengths (T, 12, 3) -> {segment: {"length_m"}} as `subject.lengths: observed`
    records them (`ptrack.body.subject.SEGMENTS`; the median over frames of the mean of both sides)."""
    x = torch.as_tensor(ref)
    d = dict(zip(SEGMENTS, lengths(x).T))

    def both(*pairs: tuple[str, str]) -> float:
        return float(torch.stack([d[p] for p in pairs]).mean(0).median())

    out = {
        "upper_arm": both(SEGMENTS[0], SEGMENTS[2]),
        "forearm": both(SEGMENTS[1], SEGMENTS[3]),
        "thigh": both(SEGMENTS[4], SEGMENTS[6]),
        "shank": both(SEGMENTS[5], SEGMENTS[7]),
        "shoulders": both(SEGMENTS[8]),
        "hips": both(SEGMENTS[9]),
        "trunk": both(SEGMENTS[10], SEGMENTS[11]),
    }
    return {n: {"length_m": v, "frames": len(ref), "std_m": None} for n, v in out.items()}


#: the root's headings (about the model's +Y) the reference is fitted from, the best kept per frame
YAWS = 8


def model_floor(
    cam: str, detections: str | None, overrides: tuple[str, ...] = ()
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """ptrack's own model started at the reference: configs/video.yaml's skeleton with the reference's own segment
    lengths (`reference_segments`), fitted to the reference's 12 keypoints in 3D (Levenberg-Marquardt from the
    rest pose under `YAWS` headings, the closest kept), then each frame polished on the camera's 2D by the kjs
    tracker's frame objective (`ptrack.estimators.kjs.model.polish`: robust reprojection, limits, collision, the
    floor; no dynamics) -> (the reference (T, 12, 3), the fit to it, the polished fit), the calibration's world.
    overrides: more key=value for the config (e.g. data.stop=N)."""
    cfg, _ = config(cam, detections, ("subject.lengths=template", *overrides))
    with tempfile.TemporaryDirectory() as tmp:
        prep = prepare_real(cfg, Path(tmp))
    assert prep.footage is not None
    W = prep.footage.world_from_model
    ref_world = reference(np.asarray(prep.footage.frames))
    prep = with_segments(prep, reference_segments(ref_world))
    prob = prep.problem
    s = make_setup(prob, cfg, KJS)
    sk, dtype = prob.skeleton, prob.observations.keypoints.dtype
    kidx = prob.keypoints.index()[body_rows(prep.footage.keypoint_set, list(prob.observations.keypoint_names))]
    ref = torch.as_tensor(ref_world @ W, dtype=dtype)  # (T, 12, 3) model frame
    T, D = ref.shape[0], sk.num_dofs
    q0 = torch.zeros(YAWS, T, D, dtype=dtype)
    q0[..., list(sk.translation_dof)] = ref[:, 6:8].mean(1)  # the root at the hips' midpoint
    q0[..., sk.dof_names.index("root.ry")] = torch.arange(YAWS, dtype=dtype)[:, None] * (2 * np.pi / YAWS) - np.pi
    target = ref.repeat(YAWS, 1, 1)

    def linearize_3d(q: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        joints, jac = joint_jacobian(sk, q)
        return (joints[:, kidx] - target).flatten(1) / 0.01, jac[:, kidx].flatten(1, 2) / 0.01

    q_fit, info = levenberg_marquardt(linearize_3d, q0.flatten(0, 1), s.lower, s.upper, max_iter=200)
    best = info.cost.view(YAWS, T).argmin(0)
    q_fit = q_fit.view(YAWS, T, D)[best, torch.arange(T)]
    with torch.no_grad():
        q_pol, _, _ = polish(s, torch.arange(T), q_fit, None, 50)

    def world(q: torch.Tensor) -> np.ndarray:
        return sk.forward_kinematics(q)[:, kidx].double().numpy() @ W.T

    return ref_world, world(q_fit), world(q_pol)


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
    print(f"2D: {source}; MPJPE / PA-MPJPE, mm, against the triangulated reference")
    print("| camera | 2D vs reference, median px | rigid | fit, acc 1 | fit, acc 10 | model fit | model polished |")
    print("|---|---|---|---|---|---|---|")
    for cam in args.cameras.split(","):
        uv, conf, P, frames = camera_inputs(cam, args.detections)
        ref = reference(frames)
        h = np.concatenate([ref, np.ones_like(ref[..., :1])], -1) @ P.T
        px = np.linalg.norm(h[..., :2] / h[..., 2:] - uv, axis=-1)[conf > 0]
        cells = [score(fit(ref, uv, conf, P, None, 0.0), ref)]
        cells += [score(fit(ref, uv, conf, P, args.sigma_px, acc), ref) for acc in (1.0, 10.0)]
        model_ref, model_fit, model_polished = model_floor(cam, args.detections)
        cells += [score(model_fit, model_ref), score(model_polished, model_ref)]
        print(f"| {cam} | {np.median(px):.1f} | {' | '.join(cells)} |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
