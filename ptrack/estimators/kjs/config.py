"""The config section of the mixture trackers (`kjs:`, for methods kjs, css and ss) and its checks. Composed into
the run's config by `ptrack.pipeline.config`."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Protocol

from ptrack.body.pose_prior import check_smoothing_table
from ptrack.costs.base import ROBUST_LOSSES
from ptrack.costs.config import CostsConfig
from ptrack.errors import InputError
from ptrack.settings import setting

#: the stages that may follow the passes (`kjs.stages`; `ptrack.estimators.kjs.lattice.STAGES` holds them), the
#: default: all three in this order
STAGE_NAMES: tuple[str, ...] = ("smooth", "recombine", "decode")


@dataclass(frozen=True)
class KjsMethodConfig:
    """Settings of the sampling trackers `kjs` (kinematic jumps + CSS diffusion), `css` and `ss`."""

    modes: int = setting(8, "K: mixture modes kept per frame")
    samples: int = setting(256, "hypotheses per frame: the K predicted modes, diffusion samples and (kjs) jump leaves")
    scale: float = setting(4.0, "covariance scale s of the diffusion (s times the inverse Gauss-Newton Hessian)")
    tail: str = setting("student", "diffusion tail: gaussian, student, cauchy")
    tail_dof: float = setting(3.0, "Student-t degrees of freedom (tail: student)")
    chains: tuple[str, ...] = setting(
        ("larm", "rarm", "lleg", "rleg", "head"), "kinematic sub-chains that may be flipped (ptrack.hypotheses.jumps)"
    )
    jumps_per_sample: int = setting(1, "chains flipped per diffusion sample, chosen by covariance voting")
    limits_mode: str = setting("prune", "jump leaves outside the joint limits: prune or project")
    polisher: str = setting("lm", "local optimiser of every hypothesis: lm (Levenberg-Marquardt) or lbfgs")
    polish_iterations: int = setting(4, "Levenberg-Marquardt iterations of every hypothesis")
    refine_iterations: int = setting(10, "further iterations of the 4K most promising distinct minima")
    distinct_mm: float = setting(0.0, "minima whose joints are all closer (mm) are one; 0: compare dofs (distinct_deg)")
    distinct_deg: float = setting(3.0, "with distinct_mm 0: minima closer than this in every dof are one")
    temperature: float = setting(1.0, "weights ∝ prior * exp(-cost / temperature)")
    weight_memory: float = setting(0.5, "reweight memory: a new mode's prior is its parent's weight ** weight_memory")
    reweight: str = setting(
        "memory", "a new mode's prior: memory (its parent's weight ** weight_memory) or mixture (the paper's)"
    )
    prior_sigma: float = setting(0.05, "the dynamics' velocity std, radians (or metres) per frame, where no table")
    dynamics: str | None = setting(
        "cmu-train", "per-dof velocity std table: cmu-train, cmu (dev clips) or null (prior_sigma for all)"
    )
    dynamics_scale: float = setting(1.5, "the table's stds are multiplied by this")
    dynamics_floor: float = setting(0.02, "least velocity std per frame from the table")
    prior_tail: str = setting("cauchy", "tails of the dynamics prior: gaussian, or a robust loss (cauchy, ...)")
    prior_tail_scale: float = setting(3.0, "where the robust tail begins, in standard deviations")
    motion_scale: float = setting(1.0, "the prior's std widened by this times each mode's last displacement")
    pose_prior_weight: float = setting(
        0.1, "weight of the CMU pose prior (ptrack.body.pose_prior) in every tracking step"
    )
    pose_mixture_weight: float = setting(
        0.0,
        "weight of the CMU pose mixture (ptrack.body.pose_mixture) in each mode's frame cost, which ranks the modes "
        "(best trajectory, weights) without moving them; 0: none",
    )
    collision_weight: float = setting(1.0, "weight of the body non-self-intersection term")
    floor_deg: float = setting(0.5, "smallest sampling std per dof (unobservable directions), degrees")
    viterbi_sigma_m: float = setting(
        0.05, "the lattice's velocity prior on the joints relative to the root: std, metres per frame and coordinate"
    )
    init: str = setting("keyframe", "keyframe: frame 0's 3D pose given; tree: rest pose fitted in view + every flip")
    start_prior_scale: float = setting(1.5, "init tree: the CMU pose prior's spread is scaled by this")
    rest_sigma: float = setting(1.0, "init tree: std around 0 of the angles the pose prior does not name, radians")
    init_yaws: int = setting(8, "init tree: headings of the rest pose tried (each also leaned forward and back)")
    init_fits: int = setting(4, "init tree: distinct fitted poses whose chains are flipped (every combination)")
    backward_pass: str = setting("always", "a second pass backwards in time: always, tree (after a tree start), never")
    smooth_scale: float = setting(0.2, "the smoother's prior std, times the dynamics'")
    recombine_sigma_m: float = setting(0.15, "recombine: velocity std on the chain's joints, metres per frame")
    stages: tuple[str, ...] = setting(
        STAGE_NAMES,
        "what follows the passes, in order: smooth (a smoother sweep over the hypotheses), recombine (each chain's "
        "reading by its own Viterbi pass), decode (posterior weights and MAP path; without it the passes' weights "
        "and the forward Viterbi path)",
    )


class KjsRunConfig(Protocol):
    """What the kjs, css and ss trackers read of the run's config: `ptrack.pipeline.config.RunConfig` is one
    (estimators sit below the pipeline and do not import it; its module checks that it fits)."""

    @property
    def kjs(self) -> KjsMethodConfig: ...

    @property
    def costs(self) -> CostsConfig: ...


def validate_kjs(kc: KjsMethodConfig) -> None:
    """Value checks of the `kjs:` section (InputError naming the key)."""
    if kc.modes < 1:
        raise InputError(f"config key 'kjs.modes' must be >= 1, got {kc.modes}")
    if kc.samples < kc.modes:
        raise InputError(f"config key 'kjs.samples' must be at least kjs.modes ({kc.modes}), got {kc.samples}")
    for key in (
        "scale",
        "tail_dof",
        "distinct_deg",
        "temperature",
        "prior_sigma",
        "floor_deg",
        "viterbi_sigma_m",
        "rest_sigma",
        "start_prior_scale",
        "prior_tail_scale",
        "dynamics_scale",
        "smooth_scale",
        "recombine_sigma_m",
    ):
        if not getattr(kc, key) > 0:
            raise InputError(f"config key 'kjs.{key}' must be positive, got {getattr(kc, key)}")
    if not kc.dynamics_floor >= 0:
        raise InputError(f"config key 'kjs.dynamics_floor' must be >= 0, got {kc.dynamics_floor}")
    check_smoothing_table(kc.dynamics, "kjs.dynamics")
    for key in ("init_yaws", "init_fits"):
        if getattr(kc, key) < 1:
            raise InputError(f"config key 'kjs.{key}' must be >= 1, got {getattr(kc, key)}")
    if kc.collision_weight < 0:
        raise InputError(f"config key 'kjs.collision_weight' must be >= 0, got {kc.collision_weight}")
    if kc.polish_iterations < 0 or kc.refine_iterations < 0 or kc.jumps_per_sample < 0:
        raise InputError(
            "config keys 'kjs.polish_iterations', 'kjs.refine_iterations' and 'kjs.jumps_per_sample' must be >= 0"
        )
    for key in ("motion_scale", "pose_prior_weight", "pose_mixture_weight", "distinct_mm"):
        if not getattr(kc, key) >= 0 or not math.isfinite(getattr(kc, key)):
            raise InputError(f"config key 'kjs.{key}' must be >= 0, got {getattr(kc, key)}")
    if not 0 <= kc.weight_memory <= 1:
        raise InputError(f"config key 'kjs.weight_memory' must be in [0, 1], got {kc.weight_memory}")
    for key, allowed in (
        ("tail", ("gaussian", "student", "cauchy")),
        ("limits_mode", ("prune", "project")),
        ("polisher", ("lm", "lbfgs")),
        ("init", ("keyframe", "tree")),
        ("backward_pass", ("tree", "always", "never")),
        ("reweight", ("mixture", "memory")),
        ("prior_tail", ("gaussian", *(n for n in ROBUST_LOSSES if n != "l2"))),
    ):
        if getattr(kc, key) not in allowed:
            raise InputError(f"config key 'kjs.{key}' must be one of {', '.join(allowed)}, got {getattr(kc, key)!r}")
    for name in kc.stages:
        if name not in STAGE_NAMES:
            raise InputError(f"config key 'kjs.stages' names {name!r}; the stages are {', '.join(STAGE_NAMES)}")
    if "decode" in kc.stages and (kc.stages.count("decode") > 1 or kc.stages[-1] != "decode"):
        raise InputError("config key 'kjs.stages': decode comes once, last (it weighs the final hypotheses)")
