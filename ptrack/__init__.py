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
    "Camera": "ptrack.camera",
    "camera_for_motion": "ptrack.camera",
    "look_at": "ptrack.camera",
    "load_config": "ptrack.config",
    "InputError": "ptrack.errors",
    "KeypointSet": "ptrack.keypoints",
    "make_keypoints": "ptrack.keypoints",
    "forward_kinematics": "ptrack.kinematics",
    "ChannelConfig": "ptrack.observations",
    "Observations": "ptrack.observations",
    "simulate_observations": "ptrack.observations",
    "estimate": "ptrack.run",
    "Motion": "ptrack.skeleton",
    "Skeleton": "ptrack.skeleton",
    "load_amc": "ptrack.skeleton",
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
    from ptrack.camera import Camera, camera_for_motion, look_at
    from ptrack.config import load_config
    from ptrack.errors import InputError
    from ptrack.keypoints import KeypointSet, make_keypoints
    from ptrack.kinematics import forward_kinematics
    from ptrack.observations import ChannelConfig, Observations, simulate_observations
    from ptrack.run import estimate
    from ptrack.skeleton import Motion, Skeleton, load_amc
