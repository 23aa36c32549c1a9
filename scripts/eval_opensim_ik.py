"""OpenSim's inverse kinematics of ptrack's one-camera TRC against the same IK of Pose2Sim's 4-camera
triangulation (issue 43's target: hip flexion and knee angles within 10 degrees RMS).

    python -m ptrack.cli run configs/video.yaml \
        observations.file=../shared/data/pose2sim/balancing/pose/cam01_json \
        camera.file=../shared/data/pose2sim/Calib_qualisys.toml camera.name=cam01 \
        subject.height_m=1.72 observations.fps=60 out_dir=runs/balancing_cam01
    python scripts/eval_opensim_ik.py runs/balancing_cam01 [--noise-mm 30] [--floor]

Both IKs are `ptrack.io.opensim_ik.inverse_kinematics` (one marker task per marker the model and the TRC
share, weights 1) on the shipped scaled model. Frames correspond by input frame number: the run's
`frames` (its TRC's Time is frame / fps) against the triangulated TRC's rows (row i is input frame i: its
Frame# i + 1, Time (i + 1) / fps). Also reported: both against the shipped `opensim_ik.mot` (Pose2Sim's own
IK setup on a filtered TRC, a looser reference), and with `--noise-mm S` the same IK of the triangulated
TRC with independent Gaussian noise of S mm on every coordinate of every marker (S * sqrt(3) mm RMS per
marker), for scale. With `--floor`, a floor under the target: the triangulated TRC with its 12 body markers
replaced by `scripts/footage_floor.py`'s fit of cam01's OpenPose 2D started at the triangulation (the other
markers left as triangulated), and, apart, by the nearest rigid body alone (no 2D). Needs the `export` extra
(opensim) and ../shared/data/pose2sim.
"""

from __future__ import annotations

import argparse
import tempfile
from pathlib import Path

import numpy as np

from ptrack.io.exporters import ExportOptions, export_run
from ptrack.io.opensim_ik import inverse_kinematics

REPO = Path(__file__).resolve().parents[1]
TRIAL = REPO / ".." / "shared" / "data" / "pose2sim" / "balancing"
ANGLES = ("hip_flexion_r", "hip_flexion_l", "knee_angle_r", "knee_angle_l", "hip_adduction_r", "hip_adduction_l")


def read_mot(path: Path) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    """(T,) times and column name -> (T,) values of an OpenSim .mot/.sto file."""
    lines = path.read_text().splitlines()
    start = next(i for i, line in enumerate(lines) if line.strip() == "endheader") + 1
    names = lines[start].split("\t")
    values = np.array([[float(v) for v in line.split("\t")] for line in lines[start + 1 :] if line.strip()])
    return values[:, 0], {n.strip(): values[:, k] for k, n in enumerate(names)}


def noisy_trc(src: Path, dst: Path, sigma_mm: float, seed: int) -> None:
    """Copy a TRC adding independent Gaussian noise of sigma_mm to every marker coordinate."""
    rng = np.random.default_rng(seed)
    lines = src.read_text().splitlines()
    out = lines[:5]
    for line in lines[5:]:
        cells = line.split("\t")
        if len(cells) < 3:
            out.append(line)
            continue
        xyz = np.array([float(c) for c in cells[2:] if c.strip()])
        xyz += rng.normal(0.0, sigma_mm / 1000.0, xyz.shape)
        out.append("\t".join([*cells[:2], *(f"{v:.6f}" for v in xyz)]))
    dst.write_text("\n".join(out) + "\n")


def floor_trc(dst: Path, cam: str, with_2d: bool) -> None:
    """The triangulated TRC with its 12 body markers replaced by `footage_floor.fit` of `cam`'s OpenPose 2D (with_2d)
    or by the nearest rigid body (not with_2d), both started at the triangulation."""
    import footage_floor  # scripts/ (this script's folder)

    uv, conf, P, frames = footage_floor.camera_inputs(cam, None)
    ref = footage_floor.reference(frames)
    fitted = footage_floor.fit(ref, uv, conf, P, 8.0 if with_2d else None, 1.0 if with_2d else 0.0)  # lab axes
    lines = (TRIAL / "triangulated.trc").read_text().splitlines()
    names = [n for n in lines[3].split("\t")[2:] if n.strip()]
    rows = {int(f): i for i, f in enumerate(frames)}
    out = lines[:5]
    for i, line in enumerate(lines[5:]):
        cells = line.split("\t")
        if len(cells) < 3 or i not in rows:
            out.append(line)
            continue
        xyz = np.array([float(c) for c in cells[2 : 2 + 3 * len(names)]]).reshape(-1, 3)
        for k, name in enumerate(footage_floor.BODY12):
            xyz[names.index(name)] = fitted[rows[i], k][[1, 2, 0]]  # lab (X, Y, Z) -> TRC (Y, Z, X)
        out.append("\t".join([*cells[:2], *(f"{v:.6f}" for v in xyz.ravel())]))
    dst.write_text("\n".join(out) + "\n")


def rms(a: dict[str, np.ndarray], b: dict[str, np.ndarray], rows_a: np.ndarray, rows_b: np.ndarray) -> list[float]:
    return [float(np.sqrt(np.mean((a[n][rows_a] - b[n][rows_b]) ** 2))) for n in ANGLES]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("run_dir", help="a ptrack run of cam01 of the balancing trial")
    ap.add_argument("--noise-mm", type=float, default=None, help="also: the triangulated TRC with this noise per axis")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--floor", action="store_true", help="also: footage_floor.py's fit of cam01, and the rigid body")
    args = ap.parse_args()
    model = TRIAL / "opensim_model_scaled.osim"
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(tmp)
        (ours_mot,) = export_run(args.run_dir, "mot", work / "ours.mot", ExportOptions(opensim=str(model)))
        inverse_kinematics(model, TRIAL / "triangulated.trc", work / "tri.mot", work)
        t_ours, ours = read_mot(ours_mot)
        t_tri, tri = read_mot(work / "tri.mot")
        t_ship, ship = read_mot(TRIAL / "opensim_ik.mot")
        fps = 60.0
        frames = np.rint(t_ours * fps).astype(int)  # input frame numbers
        ref_rows = np.rint(t_tri * fps).astype(int) - 1  # row i = input frame i
        keep = np.isin(frames, ref_rows)
        rows_ours, rows_ref = np.flatnonzero(keep), frames[keep]
        assert np.array_equal(np.rint(t_ship * fps).astype(int) - 1, ref_rows)
        table = {
            "ptrack cam01 vs IK(triangulated)": rms(ours, tri, rows_ours, rows_ref),
            "ptrack cam01 vs shipped opensim_ik.mot": rms(ours, ship, rows_ours, rows_ref),
            "IK(triangulated) vs shipped opensim_ik.mot": rms(tri, ship, rows_ref, rows_ref),
        }
        if args.noise_mm is not None:
            noisy_trc(TRIAL / "triangulated.trc", work / "noisy.trc", args.noise_mm, args.seed)
            inverse_kinematics(model, work / "noisy.trc", work / "noisy.mot", work)
            _, noisy = read_mot(work / "noisy.mot")
            table[f"IK(triangulated + {args.noise_mm:g} mm noise) vs IK(triangulated)"] = rms(
                noisy, tri, rows_ref, rows_ref
            )
        if args.floor:
            for with_2d, what in ((False, "nearest rigid body"), (True, "floor fit of cam01's 2D")):
                floor_trc(work / "floor.trc", "cam01", with_2d)
                inverse_kinematics(model, work / "floor.trc", work / "floor.mot", work)
                _, floor = read_mot(work / "floor.mot")
                table[f"IK({what}) vs IK(triangulated)"] = rms(floor, tri, rows_ref, rows_ref)
    print(f"{len(rows_ours)} frames; RMS differences in degrees")
    width = max(len(what) for what in table)
    print(" " * width + "".join(f"{n:>17s}" for n in ANGLES))
    for what, values in table.items():
        print(f"{what:{width}s}" + "".join(f"{v:17.1f}" for v in values))


if __name__ == "__main__":
    main()
