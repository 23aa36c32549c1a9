"""ptrack: 3D human motion from a single camera.

Data flows one way: data (ASF/AMC, keypoint files) -> skeleton + camera -> observations ->
costs -> estimators -> results -> metrics, exports, rerun logs.
"""

__version__ = "0.1.0"
