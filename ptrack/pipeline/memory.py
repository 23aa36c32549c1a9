"""How much memory a run will take, and how much there is.

`estimate_bytes(cfg, frames, joints, dofs, keypoints, ...)` models the dominant allocations of each method
in `ptrack.estimators.ESTIMATORS` from its settings and the clip's shapes (T frames, J joints, D dofs, K
keypoints), as an upper bound of the process's peak resident memory; `available_bytes()` is what the machine
(or its cgroup) can still give; `check_memory(cfg, problem)` refuses (`InputError`, one line naming the
settings that drive the estimate) a run that would not fit, before the estimator allocates anything.

The per-item constants below count the elements a method holds at its peak per hypothesis, trajectory frame
or window row, temporaries included; they were read off the code and then checked against the peak RSS of
real runs (`scripts/check_memory.py`, bundled clip, 2-core machine: estimate / measured peak RSS 1.3 for
frame, 1.7-2.1 for kjs and css at 256-2048 samples and 8-64 modes, 3.9 for a kjs tree start (the bound
counts every flip combination of the chains as kept; most are pruned), 1.5-1.6 for batch at 15-300 frames,
1.2-1.4 for pca at 8-256 headings). A kjs tree start with a backward pass counts its polishing twice: its two
passes may run at once, in two processes (`ptrack.estimators.kjs.track`).
"""

from __future__ import annotations

import logging
import os
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

from ptrack.errors import InputError

if TYPE_CHECKING:
    from ptrack.pipeline.config import RunConfig
    from ptrack.problem import Problem

log = logging.getLogger(__name__)

GIB = float(1 << 30)

#: the fixed cost of a run: the interpreter, torch, ptrack, the clip and its observations, metrics and the
#: rerun recording (a `method: frame` run of 15 frames peaked at 457 MiB), with a margin
FLOOR_BYTES = 600 << 20

#: the variable part counted below times this: temporaries not counted, and the allocator's freed pages that
#: it keeps (the peak RSS of the same run varies by 10-20% from run to run)
MARGIN = 2.0

#: Elements held per polished hypothesis of the mixture trackers (kjs, css, ss; and the kjs tree start) at
#: the peak of one batched Levenberg-Marquardt call, in units of: D^2 (the Hessian, its damped copy, the
#: Cholesky factor, the scale factors of the new modes), J 3 D (the joints' geometric Jacobians), 2 K D (the
#: reprojection rows) and J 12 (forward kinematics: rotations and positions, a few copies)
HYPOTHESIS_D2, HYPOTHESIS_JACOBIAN, HYPOTHESIS_ROWS, HYPOTHESIS_FK = 8, 4, 4, 4

#: Elements held per mode and frame by the trackers' lattice (both passes' modes, their merge, the smoother's
#: and the recombination's copies, the principal directions' eigendecomposition): of D^2 and J 3
LATTICE_D2, LATTICE_JOINTS = 12, 12

#: batch: trajectories linearised together (the flip branches: one chain's 4 leaves at a time,
#: `ptrack.hypotheses.branches.relax_branches`) and the elements per trajectory frame (float64) of D^2 (normal
#: equations, banded factor, marginal covariances), J 3 D (joint Jacobians) and 2 K D (weighted reprojection rows)
BATCH_BRANCHES = 4
BATCH_D2, BATCH_JACOBIAN, BATCH_ROWS = 4, 3, 2

#: pca: elements per (frame, silhouette sample, bone) of the ray-to-capsule distances and their derivatives,
#: and per Jacobian entry of a window's (or the root placement's) Levenberg-Marquardt
PCA_RAY_BONE, PCA_JACOBIAN = 24, 6


@dataclass(frozen=True)
class Need:
    """An estimate: bytes, and the settings that drive it (for the refusal's message)."""

    bytes: int
    drivers: tuple[str, ...]


def available_bytes() -> int | None:
    """Memory a new allocation can still get, in bytes: Linux's MemAvailable (/proc/meminfo), or the room
    left under the cgroup's limit (/sys/fs/cgroup/memory.max less memory.current) where that is smaller;
    elsewhere the free physical pages (os.sysconf); None where none of these can be read (no check)."""
    found: list[int] = []
    try:
        for line in Path("/proc/meminfo").read_text().splitlines():
            if line.startswith("MemAvailable:"):
                found.append(int(line.split()[1]) * 1024)
                break
    except (OSError, ValueError, IndexError):
        pass
    cgroup = Path("/sys/fs/cgroup")
    try:
        limit = (cgroup / "memory.max").read_text().strip()
        if limit != "max":
            used = int((cgroup / "memory.current").read_text().strip())
            found.append(max(int(limit) - used, 0))
    except (OSError, ValueError):
        pass
    if not found:
        try:
            found.append(os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE"))
        except (AttributeError, ValueError, OSError):
            return None
    return min(found)


def estimate_bytes(
    cfg: RunConfig,
    frames: int,
    joints: int,
    dofs: int,
    keypoints: int,
    *,
    chain_links: int = 9,
    silhouette_samples: int = 0,
    correspondences: int = 0,
) -> int:
    """Upper estimate of the peak resident memory (bytes) of running `cfg.method` on T = `frames` frames of a
    model with J `joints`, D `dofs` and K `keypoints`. chain_links: the links of the kjs chains together (a
    tree start expands every flip combination: 2^links leaves per fit); silhouette_samples: foreground samples
    per frame (pca); correspondences: point pairs per frame (pca)."""
    return _need(cfg, frames, joints, dofs, keypoints, chain_links, silhouette_samples, correspondences).bytes


def _need(
    cfg: RunConfig,
    t: int,
    j: int,
    d: int,
    k: int,
    chain_links: int,
    silhouette_samples: int,
    correspondences: int,
) -> Need:
    w = 8 if cfg.dtype == "float64" else 4
    method = cfg.method
    if method in ("kjs", "css", "ss"):
        c = cfg.kjs
        n = c.samples
        drivers = [f"kjs.samples={c.samples}", f"kjs.modes={c.modes}"]
        if c.init == "tree":  # init_fits fits, each expanded by every flip combination of the chains
            n = max(n, c.init_fits * 2 ** min(chain_links, 60) + 3 * c.init_yaws)
            drivers.append(f"kjs.init_fits={c.init_fits}")
        per_hypothesis = HYPOTHESIS_D2 * d * d + HYPOTHESIS_JACOBIAN * 3 * j * d
        per_hypothesis += HYPOTHESIS_ROWS * 2 * k * d + HYPOTHESIS_FK * 12 * j
        polish = n * per_hypothesis * w + n * n  # + the distinct minima's (n, n) table of close pairs
        if c.init == "tree" and c.backward_pass != "never":  # the two passes may polish at once (two processes)
            polish *= 2
        lattice = t * c.modes * (LATTICE_D2 * d * d + LATTICE_JOINTS * 3 * j) * w
        viterbi = 4 * c.modes * c.modes * w  # the (K, K) pairwise costs between consecutive frames
        total = polish + lattice + viterbi
    elif method == "batch":
        b = cfg.batch
        branches = BATCH_BRANCHES if (b.flip_restarts > 0 or b.uncertainty in (True, "branches")) else 1
        per_frame = BATCH_D2 * d * d + BATCH_JACOBIAN * 3 * j * d + BATCH_ROWS * 2 * k * d
        total = branches * t * per_frame * 8
        drivers = ["data.stop", "data.stride"] + ([f"batch.upsample={b.upsample}"] if b.upsample > 1 else [])
    elif method == "pca":
        p = cfg.pca
        m = cfg.motion.components
        f = min(p.window, t)
        bones = max(j - 1, 1)
        rows = 2 * len(p.joints) + silhouette_samples + 2 * correspondences  # residual rows per frame
        window = f * (silhouette_samples * bones * PCA_RAY_BONE + rows * (m + 7 * f) * PCA_JACOBIAN)
        start = p.init_yaws * (silhouette_samples * bones * PCA_RAY_BONE + rows * (m + 7) * PCA_JACOBIAN)
        whole = t * (silhouette_samples + correspondences) * bones * PCA_RAY_BONE  # the final per-frame terms
        total = (window + start + whole) * w
        drivers = [f"pca.init_yaws={p.init_yaws}", f"pca.window={p.window}"]
        if silhouette_samples:
            drivers.append(f"pca.silhouette_samples={p.silhouette_samples}")
    else:  # frame: one frame's L-BFGS at a time, the trajectory kept
        total = t * (3 * j + d + 2 * k) * w * 4 + 64 * (3 * j * d) * w
        drivers = ["data.stop", "data.stride"]
    return Need(FLOOR_BYTES + int(MARGIN * total), tuple(drivers))


def check_memory(cfg: RunConfig, problem: Problem) -> None:
    """Refuse (InputError, one line) a run of `cfg` on `problem` whose estimated peak memory
    (`estimate_bytes`) exceeds what is available (`available_bytes`); no check where that is unknown."""
    need, have = needed(cfg, problem), available_bytes()
    t = problem.observations.num_frames
    log.debug("memory: method %s needs about %.2f GiB; available %s", cfg.method, need.bytes / GIB, have)
    if have is not None and need.bytes > have:
        raise InputError(
            f"method {cfg.method} with {', '.join(need.drivers)} on {t} frames would need about "
            f"{need.bytes / GIB:.3g} GiB; this machine has {have / GIB:.3g} GiB available; lower "
            f"{_advice(cfg)}"
        )


def needed(cfg: RunConfig, problem: Problem) -> Need:
    """`estimate_bytes` of `cfg` on `problem`'s shapes (and the settings that drive it)."""
    sk, obs = problem.skeleton, problem.observations
    links = 0
    if cfg.method in ("kjs", "css", "ss") and cfg.kjs.init == "tree":
        from ptrack.hypotheses.jumps import default_chains

        try:
            links = sum(c.num_links for c in default_chains(sk, cfg.kjs.chains))
        except InputError:  # the tracker's own check names the bad key
            links = 0
    samples = 0
    if cfg.method == "pca" and obs.masks is not None and cfg.pca.silhouette_weight > 0:
        samples = cfg.pca.silhouette_samples
    pairs = 0
    if cfg.method == "pca" and problem.correspondences is not None:
        frame = problem.correspondences.frame
        pairs = int(frame.bincount().max()) if frame.numel() else 0  # the most in a frame: by_frame pads to it
    t, j, d, k = obs.num_frames, sk.num_joints, sk.num_dofs, len(problem.keypoints.names)
    return _need(cfg, t, j, d, k, links, samples, pairs)


def _advice(cfg: RunConfig) -> str:
    if cfg.method in ("kjs", "css", "ss"):
        return "kjs.samples/kjs.modes" + (" (or kjs.init_fits)" if cfg.kjs.init == "tree" else "") + " (or data.stop)"
    if cfg.method == "pca":
        return "pca.init_yaws/pca.window/pca.silhouette_samples (or data.stop)"
    return "the frames (data.stop, or a larger data.stride)"
