"""The simulated person the camera sees, when they are not the tracker's body: another skeleton (`seen_skeleton`),
other flesh (`seen_radii`) and a detector's keypoints off the joint centres (`keypoint_offsets`, `offset_keypoints`).

The simulated observations are otherwise made from the very body the tracker fits: the 2D keypoints are its joint
centres' projections and the silhouettes its own capsules'. A real person differs on all three counts:

- the skeleton: `seen_skeleton` is the tracker's template (a CMU ASF skeleton) scaled to a height with Winter's
  segment proportions, as the real-footage path scales it (`ptrack.body.subject.scale_to_height`); its joints move
  with the clip's angles and root translation, and make the 2D, the silhouettes and the ground truth;
- the flesh: the silhouettes may come from the capsules of yet another skeleton (`seen_skeleton` of another
  height) moving with the same angles, the 2D from the person's joints (a flesh model that is wrong where the
  joints are right); `seen_radii` turns each capsule's radius by a common factor and a factor of its own drawn within
  +-jitter (left and right bones alike);
- the detector: a keypoint marks a landmark on the body, not the joint centre the tracker places it at;
  `keypoint_offsets` draws, per keypoint, a point `offset_m` from the joint centre in a direction fixed in its
  joint's frame (it moves with the bone), and `offset_keypoints` places it at every frame.

Shapes: T frames, J joints, K keypoints, B bones. Randomness through the `torch.Generator` passed in.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
from torch import Tensor

from ptrack.body.skeleton import Skeleton
from ptrack.body.subject import scale_to_height


def seen_skeleton(template: Skeleton, height_m: float | None) -> Skeleton:
    """The skeleton of the person seen: `template` scaled to `height_m` with Winter's proportions (a CMU ASF
    skeleton; `ptrack.body.subject.scale_to_height`), or `template` itself for None."""
    return template if height_m is None else scale_to_height(template, height_m)


def seen_radii(
    bone_names: Sequence[str], radii: Tensor, scale: float, jitter: float, generator: torch.Generator
) -> Tensor:
    """Capsule radii (B,) of the person seen: radii (B,) times `scale` times a factor per bone drawn uniformly in
    [1 - jitter, 1 + jitter], one draw for a left bone ("l<name>") and its right one ("r<name>"). B draws are made
    whatever `jitter` (so the generator's later draws do not depend on it)."""
    u = torch.rand(len(bone_names), generator=generator, dtype=torch.float64)
    names = list(bone_names)
    first = []
    for i, n in enumerate(names):  # a right bone takes its left bone's draw
        mate = "l" + n[1:] if n[:1] == "r" else None
        first.append(names.index(mate) if mate in names else i)
    factor = 1.0 + jitter * (2.0 * u[first] - 1.0)
    return radii * scale * factor.to(radii)


def keypoint_offsets(num_keypoints: int, offset_m: float, generator: torch.Generator) -> Tensor:
    """(K, 3) float64 offsets, each of length `offset_m` in a direction drawn uniformly on the sphere, in the frame
    of the keypoint's joint. K draws are made whatever `offset_m`."""
    d = torch.randn(num_keypoints, 3, generator=generator, dtype=torch.float64)
    return offset_m * d / d.norm(dim=-1, keepdim=True).clamp_min(1e-12)


def offset_keypoints(joints: Tensor, rotations: Tensor, index: Tensor, offsets: Tensor) -> Tensor:
    """World keypoints (T, K, 3): joints (T, J, 3) and their world rotations (T, J, 3, 3), index (K,) the keypoints'
    joints, offsets (K, 3) in those joints' frames."""
    r = rotations[:, index]
    return joints[:, index] + (r @ offsets.to(r)[..., None])[..., 0]
