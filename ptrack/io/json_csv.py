"""`ptrack export --format json` and `--format csv`: a run's estimate under a versioned, documented schema.

JSON (`result.json`): one object validated by the JSON Schema shipped as `ptrack/data/result_schema.json`
(`SCHEMA_FILE`; `schema_version` "MAJOR.MINOR", a reader of 1.x reads every 1.y): units, up axis and
handedness, fps, joint and keypoint names, parents, dof names and units, the camera (K, R, t, image size and
where its focal length came from), per-frame joints and angles, per-joint uncertainty (`joint_std`, method
batch), the observed and reprojected 2D keypoints, footage runs' 3D keypoints and the trackers' hypotheses
with their weights. Arrays are frame-major nested lists (`np.asarray(d["joints"])` is (T, J, 3)).

CSV, long layout (one row per frame and joint or dof, a header row, no comments; `pandas.read_csv` reads it):
`joints.csv` frame, time_s, joint, parent, x_m, y_m, z_m, std_m (empty where the method has no uncertainty);
`angles.csv` frame, time_s, dof, value, unit (m for the root translation, rad for angles).

Everything is in the model frame (metres, right-handed, Y up), values rounded to `DECIMALS`. Field by field:
docs/export_bvh_json_csv.md.
"""

from __future__ import annotations

import csv
import json
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from ptrack.package_data import data_file

if TYPE_CHECKING:
    from ptrack.io.exporters import ExportOptions
    from ptrack.io.run_folder import RunFolder

SCHEMA_VERSION = "1.0"
#: the JSON Schema of result.json, shipped with the package
SCHEMA_FILE = data_file("result_schema.json")
#: decimals written: metres to 1 micrometre, radians to 1e-7, pixels to 1e-4, seconds to 1e-6, weights, costs
#: and the camera rotation to 1e-7
DECIMALS = {"m": 6, "rad": 7, "px": 4, "s": 6, "1": 7}


def load_schema() -> dict:
    """The JSON Schema of `--format json` (a dict, draft 2020-12)."""
    return json.loads(SCHEMA_FILE.read_text(encoding="utf-8"))


def _values(a: np.ndarray, unit: str) -> list:
    """Array -> nested lists of floats rounded to `DECIMALS[unit]`, None where not finite."""
    a = np.asarray(a, dtype=np.float64)
    r = np.round(a, DECIMALS[unit])
    if np.all(np.isfinite(a)):
        return r.tolist()
    out = r.astype(object)
    out[~np.isfinite(a)] = None
    return out.tolist()


def focal_source(run: RunFolder) -> tuple[str, str]:
    """Where the camera's focal length came from -> (source, detail): "calibration_file" or "image_size" (footage,
    as metrics.json's footage.camera says), "observations_file" (an observations .npz with its camera), "config"
    (the simulated camera's camera.focal_px)."""
    footage = run.metrics.get("footage")
    if footage:
        what = str(footage.get("camera", ""))
        return ("calibration_file" if what.startswith("file ") else "image_size"), what
    obs_file = (run.config.get("observations") or {}).get("file")
    if obs_file:
        return "observations_file", f"the camera stored in {obs_file}"
    cam = run.config.get("camera") or {}
    return "config", f"simulated camera: camera.focal_px {cam.get('focal_px')} px"


def _frame(run: RunFolder) -> str:
    if run.is_footage:
        footage = run.metrics.get("footage") or {}
        up = footage.get("up", "calibration" if footage.get("up_known") else "image")  # up_known: older runs
        world = "the calibration's world" if footage.get("extrinsics", up == "calibration") else "the camera's frame"
        return {
            "calibration": "footage: the calibration's world turned so that its up axis is +Y",
            "person": f"footage: {world} turned so that the normal of the floor fitted to the feet is +Y",
        }.get(up, f"footage without a known up axis: {world} turned so that the camera's image-up is +Y")
    return "CMU mocap world (Y up, the capture floor at Y = 0)"


def _version() -> str:
    """ptrack's installed version (from its package metadata: `ptrack.__version__` lives in a higher layer)."""
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version("ptrack")
    except PackageNotFoundError:
        return "unknown"


def result_document(run: RunFolder) -> dict:
    """The result.json object of `run` (see `SCHEMA_FILE` and docs/export_bvh_json_csv.md)."""
    a = run.arrays
    sk = run.skeleton
    angular = sk.angular_dofs()
    q = a["q"].astype(np.float64)
    source, detail = focal_source(run)
    hyp = None
    if "hypotheses" in a and "hypothesis_weights" in a:
        hyp = {
            "joints": _values(a["hypotheses"], "m"),
            "weights": _values(a["hypothesis_weights"], "1"),
            "costs": _values(a["hypothesis_costs"], "1") if "hypothesis_costs" in a else None,
        }
    kp3 = run.keypoints_model
    return {
        "schema": "ptrack.result",
        "schema_version": SCHEMA_VERSION,
        "generator": f"ptrack {_version()}",
        "method": run.method,
        "units": {"length": "m", "angle": "rad", "time": "s", "image": "px"},
        "coordinates": {
            "up_axis": "+Y",
            "handedness": "right",
            "frame": _frame(run),
            "camera_axes": "OpenCV: x right, y down, z forward; x_cam = R @ x_model + t",
        },
        "fps": run.fps,
        "num_frames": run.num_frames,
        "frames": a["frames"].astype(np.int64).tolist(),
        "times_s": _values(a["times"], "s"),
        "skeleton": {
            "joint_names": run.joint_names,
            "parents": run.parents.tolist(),
            "dof_names": [str(n) for n in a["dof_names"]],
            "dof_units": ["rad" if x else "m" for x in angular],
        },
        "keypoint_names": run.keypoint_names,
        "camera": {
            "K": _values(a["camera_K"], "px"),
            "R": _values(a["camera_R"], "1"),
            "t": _values(a["camera_t"], "m"),
            "image_size": a["image_size"].astype(np.int64).tolist(),
            "focal_source": source,
            "focal_detail": detail,
        },
        "floor_m": run.floor_m,
        "joints": _values(run.joints, "m"),
        "q": [[round(float(v), DECIMALS["rad" if ang else "m"]) for v, ang in zip(row, angular)] for row in q],
        "joint_std": _values(a["joint_std"], "m") if "joint_std" in a else None,
        "keypoints_2d": {
            "observed_px": _values(a["keypoints_observed"], "px"),
            "confidence": _values(np.nan_to_num(a["confidence"].astype(np.float64)), "1"),
            "reprojected_px": _values(a["keypoints_reprojected"], "px"),
        },
        "keypoints_3d": None if kp3 is None else _values(kp3, "m"),
        "hypotheses": hyp,
    }


def export_json(run: RunFolder, out_dir: Path, options: ExportOptions) -> list[Path]:
    """`ptrack export --format json`: result.json (see the module docstring)."""
    options.refuse("json", up=("y",))
    doc = result_document(run)
    path = out_dir / "result.json"
    path.write_text(json.dumps(doc, allow_nan=False, separators=(",", ":")) + "\n", encoding="utf-8")
    return [path]


#: joints.csv's and angles.csv's columns, in order
JOINT_COLUMNS = ("frame", "time_s", "joint", "parent", "x_m", "y_m", "z_m", "std_m")
ANGLE_COLUMNS = ("frame", "time_s", "dof", "value", "unit")


def export_csv(run: RunFolder, out_dir: Path, options: ExportOptions) -> list[Path]:
    """`ptrack export --format csv`: joints.csv and angles.csv, long layout (see the module docstring)."""
    options.refuse("csv", up=("y",))
    a = run.arrays
    frames = a["frames"].astype(np.int64)
    times = np.round(a["times"].astype(np.float64), DECIMALS["s"])
    names, parents = run.joint_names, run.parents
    joints = np.round(run.joints, DECIMALS["m"])
    std = np.round(a["joint_std"].astype(np.float64), DECIMALS["m"]) if "joint_std" in a else None
    angular = run.skeleton.angular_dofs()
    dofs = [str(n) for n in a["dof_names"]]
    q = a["q"].astype(np.float64)
    paths = [out_dir / "joints.csv", out_dir / "angles.csv"]
    with paths[0].open("w", newline="", encoding="utf-8") as f:
        w = csv.writer(f)
        w.writerow(JOINT_COLUMNS)
        for t in range(run.num_frames):
            for j, name in enumerate(names):
                parent = names[parents[j]] if parents[j] >= 0 else ""
                s = "" if std is None else repr(float(std[t, j]))
                w.writerow([frames[t], repr(float(times[t])), name, parent, *(repr(float(v)) for v in joints[t, j]), s])
    with paths[1].open("w", newline="", encoding="utf-8") as f:
        w = csv.writer(f)
        w.writerow(ANGLE_COLUMNS)
        for t in range(run.num_frames):
            for d, name in enumerate(dofs):
                unit = "rad" if angular[d] else "m"
                w.writerow([frames[t], repr(float(times[t])), name, repr(round(float(q[t, d]), DECIMALS[unit])), unit])
    return paths
