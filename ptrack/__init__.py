"""ptrack: 3D human motion from a single camera.

Data flows one way: data (ASF/AMC, keypoint files) -> skeleton + camera -> observations ->
costs -> estimators -> results -> metrics, exports, rerun logs.
"""

__version__ = "0.1.0"

from ptrack.camera import Camera, camera_for_motion, look_at
from ptrack.errors import InputError
from ptrack.keypoints import KeypointSet, make_keypoints
from ptrack.kinematics import forward_kinematics
from ptrack.observations import ChannelConfig, Observations, simulate_observations
from ptrack.skeleton import Motion, Skeleton, load_amc

__all__ = [
    "Camera", "ChannelConfig", "InputError", "KeypointSet", "Motion", "Observations", "Skeleton",
    "camera_for_motion", "forward_kinematics", "load_amc", "look_at", "make_keypoints",
    "simulate_observations",
]
