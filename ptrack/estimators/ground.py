"""The floor under a person, from an estimate of the person's motion: for footage whose camera does not say
where up is (no extrinsics, or a calibration world of unknown orientation).

A foot that stands on the floor puts its lowest point (the toe ends, the heel, `ptrack.body.subject.FLOOR_POINTS`)
on it; a foot in the air is above it. Over a sequence, the lowest foot point of every frame therefore traces
the floor from above: the floor is the plane under which none lies and on which those of the standing frames
lie. `floor_from_feet` fits it by iteratively reweighted least squares on the per-frame lowest points, the
frames more than `CONTACT_M` above the current plane down-weighted (feet in the air), in coordinates whose
second axis is the current guess of up:

    height = a x + b z + c,    minimise  sum_t w_t (y_t - a x_t - b z_t - c)^2 + N s0^2 (a^2 + b^2)

The ridge term (s0 = `SPREAD_PRIOR_M`) keeps the guess where the contacts do not span the floor: a person who
stands in one place determines its height but not its tilt, a person who walks in a line determines the tilt
along the line and little across it. With contacts spread over a metre or more the slope is the data's
(shrunk by s0^2 / (s0^2 + var), a few per cent). The result is reported as the tilt between the guess and the
fitted normal; the depth errors of the estimate the feet come from pass straight into it (a contact 10 cm too
deep, 2 m from the others, tilts the plane by about 3 degrees).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

#: a frame's lowest foot point more than this above the fitted plane counts as a foot in the air (metres)
CONTACT_M = 0.05
#: the ridge's length scale: contacts spread less than this about their mean leave the slope at the guess (metres)
SPREAD_PRIOR_M = 0.2
#: fewest frames with a foot on the floor for a fit (else None: the guess stays)
MIN_CONTACTS = 10
ITERATIONS = 10


@dataclass(frozen=True)
class GroundFit:
    """normal: (3,) unit vector, up, in the estimate's frame; height_m: the plane's offset along it (normal . p =
    height_m on the floor); tilt_deg: the angle between the guess and the normal; contacts: frames with a foot
    on the floor; spread_m: (2,) the contacts' standard deviation along the plane's two main directions."""

    normal: np.ndarray
    height_m: float
    tilt_deg: float
    contacts: int
    spread_m: np.ndarray


def floor_from_feet(feet: np.ndarray, up: np.ndarray, clearance_m: float = 0.0) -> GroundFit | None:
    """The floor plane under foot points `feet` (T, F, 3) metres (every frame's foot points, e.g. toes and heels;
    NaN rows are skipped), `up` (3,) the current guess of the up direction, clearance_m the height of the lowest
    foot point above the floor when a foot stands flat. None when fewer than MIN_CONTACTS frames are usable."""
    up = np.asarray(up, dtype=np.float64)
    up = up / np.linalg.norm(up)
    feet = np.asarray(feet, dtype=np.float64)
    feet = feet[np.isfinite(feet).all(axis=(-1, -2))]
    if len(feet) < MIN_CONTACTS:
        return None
    e1 = np.cross(up, [1.0, 0.0, 0.0] if abs(up[0]) < 0.9 else [0.0, 0.0, 1.0])
    e1 /= np.linalg.norm(e1)
    basis = np.stack([e1, up, np.cross(e1, up)])  # rows: horizontal, up, horizontal
    normal = up
    w = np.ones(len(feet))
    coef = np.zeros(3)
    for _ in range(ITERATIONS):
        low = feet[np.arange(len(feet)), np.argmin(feet @ normal, axis=1)]  # (T, 3) each frame's lowest point
        local = (low - low.mean(0)) @ basis.T  # (T, 3): x, height, z about the mean
        X = np.stack([local[:, 0], local[:, 2], np.ones(len(local))], axis=1)
        ridge = np.diag([1.0, 1.0, 0.0]) * w.sum() * SPREAD_PRIOR_M**2
        coef = np.linalg.solve(X.T @ (w[:, None] * X) + ridge, X.T @ (w * local[:, 1]))
        residual = local[:, 1] - X @ coef
        w = np.where(residual < CONTACT_M, 1.0, 0.01)  # feet in the air count little
        n_local = np.array([-coef[0], 1.0, -coef[1]])
        normal = (n_local / np.linalg.norm(n_local)) @ basis
    low = feet[np.arange(len(feet)), np.argmin(feet @ normal, axis=1)]
    heights = low @ normal
    contact = heights - np.median(heights[w > 0.5]) < CONTACT_M
    if int(contact.sum()) < MIN_CONTACTS:
        return None
    height = float(np.median(heights[contact])) - clearance_m
    on = low[contact] - low[contact].mean(0)
    flat = on - np.outer(on @ normal, normal)
    spread = np.sqrt(np.clip(np.linalg.eigvalsh(np.cov(flat.T))[1:][::-1], 0.0, None))
    tilt = math.degrees(math.acos(float(np.clip(normal @ up, -1.0, 1.0))))
    return GroundFit(normal=normal, height_m=height, tilt_deg=tilt, contacts=int(contact.sum()), spread_m=spread)
