"""A finished run folder read back: what `ptrack export` and the plots start from.

`ptrack run` writes config.yaml, metrics.json, result.npz (arrays documented in
`ptrack.pipeline.run.result_arrays`), skeleton.urdf (the estimated model, exactly: its forward kinematics of
`q` gives `joints`), result.bvh and run.rrd. `load_run(path)` reads the first four and checks that the arrays
a reader relies on are there with consistent shapes; anything else is one `InputError` naming the file.

Frames of reference: `joints` (T, J, 3) are metres in the model frame, Y up (the mocap world for CMU clips;
for footage, the calibration's world turned so that its up axis is +Y). Footage runs also hold `keypoints`
(T, K, 3), the keypoints under the input format's names in the calibration's own world, and
`world_from_model` (3, 3); `keypoints_model` gives them in the model frame.
"""

from __future__ import annotations

import json
import zipfile
from dataclasses import dataclass
from functools import cached_property
from pathlib import Path

import numpy as np
import yaml

from ptrack.errors import InputError

#: result.npz arrays every run has (see `ptrack.pipeline.run.result_arrays`)
REQUIRED = ("frames", "times", "q", "dof_names", "joints", "joint_names", "parents")


@dataclass(frozen=True)
class RunFolder:
    """A run folder's contents. arrays: result.npz's arrays by name; metrics: metrics.json; config: config.yaml."""

    path: Path
    arrays: dict[str, np.ndarray]
    metrics: dict
    config: dict

    @property
    def num_frames(self) -> int:
        return int(self.arrays["q"].shape[0])

    @property
    def fps(self) -> float:
        """Frames per second, exactly as the input had it (older runs without `fps`: from the times)."""
        if "fps" in self.arrays:
            return float(self.arrays["fps"])
        times = self.arrays["times"].astype(np.float64)
        return float(1.0 / np.median(np.diff(times))) if len(times) > 1 else 30.0

    @property
    def method(self) -> str:
        return str(self.metrics.get("method", self.config.get("method", "")))

    @property
    def joints(self) -> np.ndarray:
        """(T, J, 3) float64 metres, model frame (Y up)."""
        return self.arrays["joints"].astype(np.float64)

    @property
    def joint_names(self) -> list[str]:
        return [str(n) for n in self.arrays["joint_names"]]

    @property
    def parents(self) -> np.ndarray:
        """(J,) int: each joint's parent index, -1 for the root."""
        return self.arrays["parents"].astype(np.int64)

    @property
    def is_footage(self) -> bool:
        """True for a run on real keypoints (it holds `keypoints` under the input format's names)."""
        return "keypoints" in self.arrays

    @property
    def keypoint_names(self) -> list[str]:
        return [str(n) for n in self.arrays["keypoint_names"]]

    @property
    def keypoints_model(self) -> np.ndarray | None:
        """(T, K, 3) float64 metres: a footage run's keypoints in the model frame (Y up); None for other runs."""
        if not self.is_footage:
            return None
        return self.arrays["keypoints"].astype(np.float64) @ self.arrays["world_from_model"].astype(np.float64)

    @property
    def floor_m(self) -> float | None:
        """The floor's height along the model's +Y when the run knew it (footage with a calibrated up axis)."""
        footage = self.metrics.get("footage") or {}
        floor = footage.get("floor_m")
        return None if floor is None else float(floor)

    @cached_property
    def skeleton(self):
        """The estimated model (`ptrack.body.skeleton.Skeleton`) from skeleton.urdf; q (T, D) are its dofs."""
        from ptrack.body.skeleton import Skeleton

        path = self.path / "skeleton.urdf"
        if not path.is_file():
            raise InputError(f"{self.path} has no skeleton.urdf (a run made before ptrack wrote it): run it again")
        sk = Skeleton.from_urdf(path)
        if sk.num_dofs != self.arrays["q"].shape[1]:
            raise InputError(
                f"{path} has {sk.num_dofs} dofs but result.npz's q has {self.arrays['q'].shape[1]}: "
                "the files are not from the same run"
            )
        return sk


def load_run(path: str | Path) -> RunFolder:
    """Read a run folder written by `ptrack run` (see the module docstring)."""
    folder = Path(path)
    if not folder.is_dir():
        raise InputError(f"{folder} is not a folder (a ptrack run folder holds result.npz and metrics.json)")
    missing = [n for n in ("result.npz", "metrics.json", "config.yaml") if not (folder / n).is_file()]
    if missing:
        raise InputError(f"{folder} is not a ptrack run folder: no {', '.join(missing)}")
    try:
        with np.load(folder / "result.npz", allow_pickle=False) as z:
            arrays = {k: z[k] for k in z.files}
    except (OSError, ValueError, zipfile.BadZipFile, EOFError) as e:
        raise InputError(f"{folder / 'result.npz'} is not a readable npz file: {e}") from None
    absent = [k for k in REQUIRED if k not in arrays]
    if absent:
        raise InputError(f"{folder / 'result.npz'} lacks {', '.join(absent)}: not a ptrack result")
    try:
        metrics = json.loads((folder / "metrics.json").read_text(encoding="utf-8"))
        config = yaml.safe_load((folder / "config.yaml").read_text(encoding="utf-8"))
    except (OSError, ValueError, yaml.YAMLError) as e:
        raise InputError(f"{folder}: metrics.json or config.yaml is malformed: {e}") from None
    if not isinstance(metrics, dict) or not isinstance(config, dict):
        raise InputError(f"{folder}: metrics.json and config.yaml must each hold a mapping")
    t, j = arrays["joints"].shape[:2] if arrays["joints"].ndim == 3 else (-1, -1)
    if (
        arrays["q"].ndim != 2
        or arrays["q"].shape[0] != t
        or arrays["joints"].shape[-1] != 3
        or len(arrays["joint_names"]) != j
        or len(arrays["parents"]) != j
        or len(arrays["times"]) != t
        or arrays["q"].shape[1] != len(arrays["dof_names"])
    ):
        raise InputError(f"{folder / 'result.npz'}: its arrays' shapes disagree (q, joints, names, times)")
    return RunFolder(path=folder, arrays=arrays, metrics=metrics, config=config)
