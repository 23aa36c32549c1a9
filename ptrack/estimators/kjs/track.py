"""The mixture trackers' loop over the frames (forward, then backward), what follows the passes, and the
three estimators `kjs`, `css` and `ss` (the package docstring)."""

from __future__ import annotations

from collections.abc import Callable, Iterable

import torch
from torch import Tensor

from ptrack.estimators.kjs.config import KjsRunConfig
from ptrack.estimators.kjs.lattice import STAGES, best_path, lead_pass, make_lattice, principal_directions
from ptrack.estimators.kjs.model import CSS, KJS, SS, Strategy, make_setup
from ptrack.estimators.kjs.start import backward_start, feed_backward, first_modes
from ptrack.estimators.kjs.step import merge_mixtures, track_step
from ptrack.hypotheses.mixture import Modes
from ptrack.problem import Estimate, Problem
from ptrack.threads import one_thread


def track(
    problem: Problem,
    cfg: KjsRunConfig,
    generator: torch.Generator,
    strategy: Strategy,
    progress: Callable[[Iterable], Iterable] = lambda x: x,
) -> Estimate:
    """Run the tracker `strategy` over every frame of `problem` (`ptrack.estimators.kjs`' docstring), on one
    intra-op thread (`ptrack.threads.one_thread`): its products are small batched ones, and
    `scripts/bench_kjs.py` measured 6.1 fps on one thread and on two on an idle 2-core machine, but
    0.7 fps on two threads when another job held a core.

    With the Levenberg-Marquardt polisher nothing here needs autograd (the Jacobians are closed form), so
    the tracker runs in `torch.inference_mode`, which spares torch the view and version bookkeeping of each
    linearisation's ~650 small operations: the same results bit for bit, and `scripts/bench_kjs.py` 27.6 ->
    25.3 s (paired runs). The result's tensors are copied out of inference mode, so callers may use them
    freely; the caches it fills (FK plan, Jacobian and IK tables) are built outside it."""
    with one_thread(), torch.inference_mode(cfg.kjs.polisher == "lm"):  # lbfgs differentiates the cost
        est = _track(problem, cfg, generator, strategy, progress)
    return _ordinary(est)


def _ordinary(est: Estimate) -> Estimate:
    """Copies of an Estimate's tensors (also those in its dict fields) made outside inference mode:
    inference tensors cannot be modified in place or saved for backward outside it."""

    def copy(x):
        if isinstance(x, Tensor):
            return x.clone()
        if isinstance(x, dict):
            return {k: copy(v) for k, v in x.items()}
        return x

    return est._replace(**{k: copy(v) for k, v in est._asdict().items()})


def _track(
    problem: Problem,
    cfg: KjsRunConfig,
    generator: torch.Generator,
    strategy: Strategy,
    progress: Callable[[Iterable], Iterable],
) -> Estimate:
    s = make_setup(problem, cfg, strategy)
    sk, obs = problem.skeleton, problem.observations
    k = cfg.kjs
    steps = range(obs.num_frames)
    backward = k.backward_pass == "always" or (k.backward_pass == "tree" and k.init == "tree")
    schedule = [(t, False) for t in steps] + ([(t, True) for t in reversed(steps)] if backward else [])
    passes: list[list[tuple[Modes, Tensor]]] = [[], []]  # forward, backward (in reverse time order)
    modes = None
    for t, back in progress(schedule):
        if modes is None:
            modes, counts = first_modes(s, strategy), torch.zeros(len(s.chains), dtype=torch.long)
        elif back and not passes[1]:  # the forward pass's last modes (and a tree start there: backward_start)
            modes, counts = backward_start(s, modes, strategy), torch.zeros_like(counts)
        elif back and k.init == "keyframe":  # from its own modes of frame t+1 and the forward pass's (`feed_backward`)
            modes, counts = track_step(
                s, t, feed_backward(s, modes, passes[0][t + 1][0]), strategy, generator, orders=True
            )
        else:
            modes, counts = track_step(s, t, modes, strategy, generator)
        passes[back].append((modes, counts.to(modes.q.device)))
    forward = [m for m, _ in passes[0]]
    jumps = [c for _, c in passes[0]]
    lat = make_lattice(s, forward)
    path, cost = best_path(s, lat)
    if backward:  # the hypotheses of both passes, the best trajectory's mode first in each frame (`merge_mixtures`)
        lead, other = forward, [m for m, _ in reversed(passes[1])]
        if k.init == "tree":
            swap, path = lead_pass(s, path, cost, lat.joints, other)
            lead, other = (other, lead) if swap else (lead, other)
        lat = make_lattice(s, [merge_mixtures(s, a, b, int(p)) for a, b, p in zip(lead, other, path)])
        path = torch.zeros_like(path)
        jumps = [a + b for a, (_, b) in zip(jumps, reversed(passes[1]))]
    for name in k.stages:  # the named stages after the passes (`lattice.STAGES`), in the order given
        lat, path = STAGES[name](s, lat, path)
    hq, hw, hc, hl, hyp_joints = lat
    with torch.no_grad():
        frames = torch.arange(hq.shape[0], device=hq.device)
        joints = hyp_joints[frames, path]
        directions = principal_directions(sk, hq, hl, k.scale)
    q = hq[frames, path]
    return Estimate(
        q=q,
        joints=joints,
        cost=hc[frames, path],
        terms={"mode_cost": hc[frames, path]},
        hypotheses=hyp_joints,
        hypothesis_weights=hw,
        hypothesis_costs=hc,
        hypothesis_directions=directions,
        jumps={c.name: x for c, x in zip(s.chains, torch.stack(jumps).T)} if strategy.jumps else None,
    )


def estimate_kjs(problem: Problem, cfg: KjsRunConfig, generator: torch.Generator, progress=lambda x: x) -> Estimate:
    """`method: kjs`: kinematic jump sampling with CSS diffusion."""
    return track(problem, cfg, generator, KJS, progress)


def estimate_css(problem: Problem, cfg: KjsRunConfig, generator: torch.Generator, progress=lambda x: x) -> Estimate:
    """`method: css`: covariance scaled sampling only, same hypothesis budget."""
    return track(problem, cfg, generator, CSS, progress)


def estimate_ss(problem: Problem, cfg: KjsRunConfig, generator: torch.Generator, progress=lambda x: x) -> Estimate:
    """`method: ss`: spherical sampling only, same hypothesis budget and core volume."""
    return track(problem, cfg, generator, SS, progress)
