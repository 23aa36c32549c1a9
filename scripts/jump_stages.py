"""How many kinematic-jump leaves survive each stage of a kjs tracking step (issue 41, item 4).

The forward filter of `method: kjs` (frame 0's keyframe start, then `track_step` per frame) runs on the first
frames of a few clips, once with `kjs.limits_mode: prune` and once with `project`. Each step is run by
`counted_step`, a copy of `ptrack.estimators.kjs.step.track_step` that counts, and whose jumps are a copy of
`_jump` that counts; both copies are checked against the tracker's own functions (the same generator state
gives the same leaves and the same modes: `--check`, and tests/test_jump_stages.py). Stages of the flipped
leaves (leaf 0, the sample itself, is not counted as a jump leaf):

  grown      flipped leaves of the interpretation trees: each jumped sample x (2^n - 1)
  repeat     not unique: a flipped link had one solution: its end unobserved (a missing keypoint), else a ray
             missing its sphere (the sample's parent joint too far off the ray: `missed`), else tangent
  infeasible unique, but an unflipped link's ray misses its sphere
  tree       unique and feasible
  ik         closed-form IK lands the chain joints on the tree's positions (`exact`)
  limits     within the joint limits (prune keeps only these; project clamps the others and keeps them)
  kept       what `_jump` returns
  budget     within the `kjs.samples` budget (`track_step` cuts the hypotheses after the diffusion
             samples and the leaves at samples - K)
  presel     among the 4K distinct minima of lowest weight after the first polish (`select_modes`)
  modes      among the K modes after refining (`select_modes`: distinct, heaviest)

    python scripts/jump_stages.py                                  # 3 held-out clips, 16 frames each
    python scripts/jump_stages.py --clips 35_01 --frames 8 --check
"""

from __future__ import annotations

import argparse
import time
from dataclasses import dataclass, field
from pathlib import Path

import torch
from torch import Tensor

from ptrack.estimators.kjs.model import (
    KJS,
    Setup,
    Strategy,
    distinct_poses,
    make_modes,
    make_setup,
    polish,
    select_modes,
)
from ptrack.estimators.kjs.start import first_modes
from ptrack.estimators.kjs.step import _chain_votes, _diffuse, _jump, prior_weights, track_step
from ptrack.hypotheses.ik import chain_ik
from ptrack.hypotheses.jumps import interpretation_tree, joint_observations
from ptrack.hypotheses.mixture import Modes
from ptrack.pipeline.config import load_config
from ptrack.pipeline.evaluate import asf_for
from ptrack.pipeline.run import prepare

ROOT = Path(__file__).resolve().parents[1]
CMU = ROOT.parent / "shared" / "data" / "cmu" / "subjects"
#: held-out clips (configs/clips/heldout_batch.txt): a walk, a jump, a kick
CLIPS = ("35_01", "118_01", "135_04")
JUMP_STAGES = (
    *("jumped", "grown", "repeat", "unobserved", "missed", "infeasible"),
    *("tree", "ik", "limits", "projected", "kept"),
)
#: where a hypothesis of a step came from
ORIGINS = ("mode", "diffusion", "jump")


@dataclass
class Counts:
    """Counts summed over steps: the jump stages, and per origin the hypotheses at each later stage."""

    steps: int = 0
    jump: dict[str, int] = field(default_factory=lambda: dict.fromkeys(JUMP_STAGES, 0))
    stage: dict[str, dict[str, int]] = field(
        default_factory=lambda: {s: dict.fromkeys(ORIGINS, 0) for s in ("budget", "presel", "modes", "heaviest")}
    )
    distinct: int = 0  # distinct minima among all polished hypotheses (before the 4K cut)
    frames_with_jump_mode: int = 0
    best: dict[str, int] = field(default_factory=lambda: dict.fromkeys(ORIGINS, 0))  # mode nearest the truth

    def add(self, other: Counts) -> None:
        self.steps += other.steps
        self.distinct += other.distinct
        self.frames_with_jump_mode += other.frames_with_jump_mode
        for k, v in other.jump.items():
            self.jump[k] += v
        for s, d in other.stage.items():
            for k, v in d.items():
                self.stage[s][k] += v
        for k, v in other.best.items():
            self.best[k] += v


def counted_jump(
    s: Setup, t: int, q: Tensor, parent: Tensor, modes: Modes, gen: torch.Generator, per_sample: int, c: Counts
) -> tuple[Tensor, Tensor, Tensor]:
    """`ptrack.estimators.kjs.step._jump`, line for line, counting the flipped leaves at each stage into c."""
    prob = s.problem
    sk, obs = prob.skeleton, prob.observations
    counts = torch.zeros(len(s.chains), dtype=torch.long, device=q.device)
    if per_sample == 0 or not s.chains:
        return q, parent, counts
    px, conf = joint_observations(prob.keypoints, obs.keypoints[t], obs.confidence[t], sk.num_joints)
    probs = _chain_votes(s, modes.chol)[parent]
    picks = torch.multinomial(
        probs.double().cpu(), min(per_sample, len(s.chains)), replacement=False, generator=gen
    ).to(q.device)
    out_q, out_parent = [q], [parent]
    joints = sk.forward_kinematics(q)
    for ci, (chain, plan) in enumerate(zip(s.chains, s.plans)):
        rows = (picks == ci).any(-1).nonzero()[:, 0]
        if rows.numel() == 0:
            continue
        tree = interpretation_tree(chain, joints[rows], obs.camera, px, conf)
        ik = chain_ik(plan, q[rows], tree.positions, mode=s.cfg.kjs.limits_mode)
        keep = ik.keep & tree.unique & ~tree.infeasible.any(-1)
        keep[:, 0] = False
        flipped = torch.ones_like(keep)
        flipped[:, 0] = False
        in_tree = flipped & tree.unique & ~tree.infeasible.any(-1)
        c.jump["jumped"] += rows.numel()
        c.jump["grown"] += int(flipped.sum())
        c.jump["repeat"] += int((flipped & ~tree.unique).sum())
        # repeats because a flipped link's end was not observed (a missing keypoint: it cannot flip)
        bits = torch.arange(keep.shape[1], device=q.device)[:, None] >> torch.arange(chain.num_links, device=q.device)
        unseen = ((bits & 1).bool()[None] & ~tree.observed[:, None, :]).any(-1)  # (S', L)
        c.jump["unobserved"] += int((flipped & ~tree.unique & unseen).sum())
        c.jump["missed"] += int((flipped & ~tree.unique & ~unseen & tree.infeasible.any(-1)).sum())
        c.jump["infeasible"] += int((flipped & tree.unique & tree.infeasible.any(-1)).sum())
        c.jump["tree"] += int(in_tree.sum())
        c.jump["ik"] += int((in_tree & ik.exact).sum())
        c.jump["limits"] += int((in_tree & ik.exact & ik.in_limits).sum())
        c.jump["projected"] += int((in_tree & ik.exact & ik.projected).sum())
        c.jump["kept"] += int(keep.sum())
        idx = keep.nonzero()
        out_q.append(ik.q[idx[:, 0], idx[:, 1]])
        out_parent.append(parent[rows][idx[:, 0]])
        counts[ci] = idx.shape[0]
    return torch.cat(out_q), torch.cat(out_parent), counts


def _tally(c: Counts, stage: str, origin: Tensor) -> None:
    for i, name in enumerate(ORIGINS):
        c.stage[stage][name] += int((origin == i).sum())


def counted_step(
    s: Setup, t: int, modes: Modes, strategy: Strategy, gen: torch.Generator, truth: Tensor | None = None
) -> tuple[Modes, Tensor, Counts]:
    """`ptrack.estimators.kjs.step.track_step` (without `orders`), line for line, counting where each
    hypothesis came from (`ORIGINS`) at each stage. truth (J, 3): frame t's true joints, to count which
    origin the mode nearest them had. -> modes, flipped leaves kept per chain (C,), counts."""
    c = Counts(steps=1)
    k = s.cfg.kjs
    obs = s.problem.observations
    predicted = modes.q  # the dynamics' prediction: constant position
    counts = torch.zeros(len(s.chains), dtype=torch.long, device=predicted.device)
    if not bool((obs.confidence[t] > 0).any()):
        return modes._replace(q=predicted), counts, c
    centres = modes._replace(q=predicted)
    budget = k.samples - modes.q.shape[0]
    if strategy.jumps and s.chains and k.jumps_per_sample > 0:
        leaves = max(2 ** max(ch.num_links for ch in s.chains) - 1, 1) * min(k.jumps_per_sample, len(s.chains))
        n_diffuse = max(budget // (1 + leaves), 1)
    else:
        n_diffuse = budget
    q, parent = _diffuse(s, centres, n_diffuse, strategy, gen)
    n_samples = q.shape[0]
    if strategy.jumps:
        q, parent, counts = counted_jump(s, t, q, parent, centres, gen, k.jumps_per_sample, c)
        q, parent = q[:budget], parent[:budget]
    idx = torch.arange(modes.q.shape[0], device=q.device)
    origin = torch.cat(
        [
            torch.zeros(modes.q.shape[0], dtype=torch.long),
            torch.ones(n_samples, dtype=torch.long),
            torch.full((max(q.shape[0] - n_samples, 0),), 2, dtype=torch.long),
        ]
    )[: modes.q.shape[0] + q.shape[0]]
    q = torch.cat([predicted, q])
    parent = torch.cat([idx, parent])
    _tally(c, "budget", origin)
    sigma = torch.sqrt(s.dynamics_sigma**2 + (k.motion_scale * modes.velocity) ** 2)
    q, cost, _ = polish(s, t, q, predicted[parent], k.polish_iterations, sigma[parent], tracking=True)
    c.distinct = int(distinct_poses(s, q, cost).numel())
    best, _ = select_modes(s, q, cost, prior_weights(s, q, parent, modes.weight, predicted, sigma), 4 * k.modes)
    q, parent, origin = q[best], parent[best], origin[best]
    _tally(c, "presel", origin)
    q, cost, hessian = polish(s, t, q, predicted[parent], k.refine_iterations, sigma[parent], tracking=True)
    log_prior = prior_weights(s, q, parent, modes.weight, predicted, sigma)
    keep, w = select_modes(s, q, cost, log_prior, k.modes)
    if keep.numel() == 0:
        return modes._replace(q=predicted), counts, c
    _tally(c, "modes", origin[keep])
    _tally(c, "heaviest", origin[keep][:1])  # select_modes returns the heaviest first
    c.frames_with_jump_mode = int(bool((origin[keep] == 2).any()))
    if truth is not None:
        joints = s.problem.skeleton.forward_kinematics(q[keep])
        err = (joints - truth).norm(dim=-1).mean(-1)
        c.best[ORIGINS[int(origin[keep][int(err.argmin())])]] += 1
    return make_modes(s, q[keep], cost[keep], hessian[keep], w, modes.q[parent[keep]]), counts, c


def same_modes(a: Modes, b: Modes) -> bool:
    return all(torch.allclose(x, y, rtol=1e-9, atol=1e-9) for x, y in zip(a, b))


def run_clip(
    amc: Path, limits_mode: str, frames: int, seed: int, check: bool = False, overrides: tuple[str, ...] = ()
) -> Counts:
    """The forward filter of configs/eval_kjs.yaml (2 px noise, 10% missing) on the first `frames` frames of
    `amc` with `kjs.limits_mode` -> counts summed over its steps (frames 1..frames-1). check: every step is
    also run by `track_step` and `_jump` from the same generator state, and must give the same result."""
    cfg = load_config(
        ROOT / "configs" / "eval_kjs.yaml",
        [
            f"data.amc={amc}",
            f"data.asf={asf_for(amc)}",
            f"data.stop={4 * frames}",
            f"kjs.limits_mode={limits_mode}",
            f"seed={seed}",
            *overrides,
        ],
    )
    prep = prepare(cfg)
    s = make_setup(prep.problem, cfg, KJS)
    gen = torch.Generator().manual_seed(cfg.seed + 1)  # as `ptrack.pipeline.run.estimate`
    total = Counts()
    with torch.inference_mode():
        modes = first_modes(s, KJS)
        for t in range(1, prep.problem.observations.num_frames):
            truth = None if prep.gt_joints is None else prep.gt_joints[t].to(modes.q)
            if check:
                state = gen.get_state()
                ref, _ = track_step(s, t, modes, KJS, gen)
                gen.set_state(state)
                check_jump(s, t, modes, gen)
                gen.set_state(state)
            new, _, c = counted_step(s, t, modes, KJS, gen, truth)
            if check and not same_modes(new, ref):
                raise AssertionError(f"{amc.stem} frame {t}: counted_step differs from track_step")
            modes = new
            total.add(c)
    return total


def check_jump(s: Setup, t: int, modes: Modes, gen: torch.Generator) -> None:
    """`counted_jump` against `_jump` on frame t's diffusion samples, from the same generator state."""
    k = s.cfg.kjs
    centres = modes  # constant position: the prediction is the mode itself
    q, parent = _diffuse(s, centres, 32, KJS, gen)
    state = gen.get_state()
    a = _jump(s, t, q, parent, centres, gen, k.jumps_per_sample)
    gen.set_state(state)
    b = counted_jump(s, t, q, parent, centres, gen, k.jumps_per_sample, Counts())
    if not all(torch.equal(x, y) for x, y in zip(a, b)):
        raise AssertionError(f"frame {t}: counted_jump differs from _jump")


def table(results: dict[str, Counts]) -> str:
    """Markdown: one row per limits mode."""
    head = (
        "| limits_mode | steps | samples jumped | leaves grown "
        "| repeats: unobserved / ray missed / tangent | infeasible "
        "| tree (unique, feasible) | IK exact | within limits "
        "| projected | kept by _jump | within budget | hypotheses polished | distinct minima (all) "
        "| pre-selection 4K: jump / diffusion / mode "
        "| K modes: jump / diffusion / mode | heaviest mode a jump leaf | frames with a jump-leaf mode "
        "| mode nearest truth: jump / diffusion / mode |"
    )
    lines = [head, "|" + "---|" * (head.count("|") - 1)]
    for mode, c in results.items():
        j, st = c.jump, c.stage
        n = max(c.steps, 1)

        def per(x):
            return f"{x / n:.1f}"

        def trio(d):
            return f"{per(d['jump'])} / {per(d['diffusion'])} / {per(d['mode'])}"

        mk = sum(st["modes"].values())
        lines.append(
            f"| {mode} | {c.steps} | {per(j['jumped'])} | {per(j['grown'])} "
            f"| {per(j['unobserved'])} / {per(j['missed'])} / {per(j['repeat'] - j['unobserved'] - j['missed'])} "
            f"| {per(j['infeasible'])} | {per(j['tree'])} | {per(j['ik'])} "
            f"| {per(j['limits'])} | {per(j['projected'])} | {per(j['kept'])} | {per(st['budget']['jump'])} "
            f"| {per(sum(st['budget'].values()))} "
            f"| {per(c.distinct)} | {trio(st['presel'])} | {trio(st['modes'])} "
            f"| {st['heaviest']['jump'] / n:.0%} | {c.frames_with_jump_mode / n:.0%} "
            f"| {c.best['jump'] / n:.0%} / {c.best['diffusion'] / n:.0%} / {c.best['mode'] / n:.0%} |"
            if mk
            else f"| {mode} | {c.steps} | (no modes) |"
        )
    return "\n".join(lines)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--clips", nargs="+", default=list(CLIPS), help="CMU clip names (subject_trial)")
    ap.add_argument("--frames", type=int, default=16, help="frames per clip (30 fps, AMC stride 4)")
    ap.add_argument("--seeds", type=int, nargs="+", default=[0])
    ap.add_argument("--check", action="store_true", help="check every step against track_step and _jump")
    args = ap.parse_args()
    torch.set_num_threads(1)
    t0 = time.time()
    results: dict[str, Counts] = {}
    per_clip: dict[tuple[str, str], Counts] = {}
    for mode in ("prune", "project"):
        results[mode] = Counts()
        for clip in args.clips:
            for seed in args.seeds:
                amc = CMU / clip.split("_")[0] / f"{clip}.amc"
                c = run_clip(amc, mode, args.frames, seed, args.check)
                per_clip[(mode, f"{clip} seed {seed}")] = c
                results[mode].add(c)
                print(f"{mode} {clip} seed {seed}: done ({time.time() - t0:.0f} s)", flush=True)
    print(f"\nPer step (mean over {args.frames - 1} steps x {len(args.clips)} clips x {len(args.seeds)} seeds):\n")
    print(table(results))
    print("\nPer clip:\n")
    print(table({f"{m} {name}": c for (m, name), c in per_clip.items()}))
    print(f"\n{time.time() - t0:.0f} s")


if __name__ == "__main__":
    main()
