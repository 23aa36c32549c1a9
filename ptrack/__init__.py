"""ptrack: 3D human motion from a single camera.

Data flows one way: data (ASF/AMC, keypoint files) -> skeleton + camera -> observations ->
costs -> estimators -> results -> metrics, exports, rerun logs.

The names below are imported on first use, so that `import ptrack` (and the command line's `--help`)
does not load torch.
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING

__version__ = "0.1.0"

#: public name -> the module that defines it
_EXPORTS = {
    "Camera": "ptrack.observe.camera",
    "camera_for_motion": "ptrack.observe.camera",
    "look_at": "ptrack.observe.camera",
    "load_config": "ptrack.pipeline.config",
    "InputError": "ptrack.errors",
    "KeypointSet": "ptrack.body.keypoints",
    "make_keypoints": "ptrack.body.keypoints",
    "forward_kinematics": "ptrack.body.kinematics",
    "ChannelConfig": "ptrack.observe.observations",
    "Observations": "ptrack.observe.observations",
    "simulate_observations": "ptrack.observe.observations",
    "estimate": "ptrack.pipeline.run",
    "Motion": "ptrack.body.skeleton",
    "Skeleton": "ptrack.body.skeleton",
    "load_amc": "ptrack.body.skeleton",
    "read_keypoints": "ptrack.observe.keypoint_files",
    "select_person": "ptrack.observe.people",
    "read_camera": "ptrack.observe.camera_files",
    "detect": "ptrack.observe.detector",
    "load_run": "ptrack.io.run_folder",
    "export_run": "ptrack.io.exporters",
    "ExportOptions": "ptrack.io.exporters",
}

__all__ = sorted(_EXPORTS)


def __getattr__(name: str):
    if name in _EXPORTS:
        value = getattr(importlib.import_module(_EXPORTS[name]), name)
        globals()[name] = value
        return value
    raise AttributeError(f"module 'ptrack' has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted({*globals(), *_EXPORTS})


if TYPE_CHECKING:
    from ptrack.body.keypoints import KeypointSet, make_keypoints
    from ptrack.body.kinematics import forward_kinematics
    from ptrack.body.skeleton import Motion, Skeleton, load_amc
    from ptrack.errors import InputError
    from ptrack.io.exporters import ExportOptions, export_run
    from ptrack.io.run_folder import load_run
    from ptrack.observe.camera import Camera, camera_for_motion, look_at
    from ptrack.observe.camera_files import read_camera
    from ptrack.observe.detector import detect
    from ptrack.observe.keypoint_files import read_keypoints
    from ptrack.observe.observations import ChannelConfig, Observations, simulate_observations
    from ptrack.observe.people import select_person
    from ptrack.pipeline.config import load_config
    from ptrack.pipeline.run import estimate
