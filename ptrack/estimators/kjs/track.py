"""The mixture trackers' loop over the frames (forward, then backward), what follows the passes, and the
three estimators `kjs`, `css` and `ss` (the package docstring)."""

from __future__ import annotations

import functools
import itertools
from collections.abc import Callable, Iterable, Sequence

import torch
from torch import Tensor

from ptrack.estimators.kjs.config import KjsRunConfig
from ptrack.estimators.kjs.lattice import STAGES, best_path, lead_pass, make_lattice, principal_directions
from ptrack.estimators.kjs.model import CSS, KJS, SS, Setup, Strategy, make_setup
from ptrack.estimators.kjs.start import backward_start, feed_backward, first_modes
from ptrack.estimators.kjs.step import merge_mixtures, track_step
from ptrack.hypotheses.mixture import Modes
from ptrack.problem import Estimate, Problem
from ptrack.threads import in_two_processes, one_thread, parallel_processes


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
    0.7 fps on two threads when another job held a core. The second core serves the two passes after a tree start
    instead: they run at once, in two processes, each on one thread (`ptrack.threads.in_two_processes`), when the
    thread budget this replaces is 2 or more.

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
    k = cfg.kjs
    steps = range(problem.observations.num_frames)
    backward = k.backward_pass == "always" or (k.backward_pass == "tree" and k.init == "tree")
    forward_pass = functools.partial(run_pass, s, strategy, steps, generator)
    passes: list[list[tuple[Modes, Tensor]]]
    if not backward:
        passes = [forward_pass(progress=progress), []]
    elif k.init == "tree":  # two passes of their own (`run_pass`), the backward one with its own generator
        own = torch.Generator(generator.device).manual_seed(_seed(generator))
        backward_pass = functools.partial(run_pass, s, strategy, steps[::-1], own)
        if parallel_processes(problem.observations.keypoints.device):  # at once: the same passes, in half the time
            back, ahead = in_two_processes(backward_pass, functools.partial(forward_pass, progress=progress))
            passes = [ahead, back]
        else:
            along = _one_display(progress, len(steps))
            passes = [forward_pass(progress=along), backward_pass(progress=along)]
    else:  # after a keyframe start: from the forward pass's last modes, fed its modes on the way
        along = _one_display(progress, len(steps))
        ahead = forward_pass(progress=along)
        passes = [ahead, run_pass(s, strategy, steps[::-1], generator, feed=ahead, progress=along)]
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
        directions = principal_directions(problem.skeleton, hq, hl, k.scale)
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


def run_pass(
    s: Setup,
    strategy: Strategy,
    frames: Sequence[int],
    generator: torch.Generator,
    feed: list[tuple[Modes, Tensor]] | None = None,
    progress: Callable[[Iterable], Iterable] = lambda x: x,
) -> list[tuple[Modes, Tensor]]:
    """One pass of the tracker over `frames` (forwards or backwards in time) -> each frame's (modes, flipped
    leaves per chain (C,)), in the pass's order.

    It starts from a keyframe on frame 0, or with a tree start on the pass's first frame with a detection (the
    frames before that one, in the pass's order, take its modes) (`first_modes`). feed: the forward pass's
    output, for the backward pass after a keyframe start: that pass starts from the forward pass's last modes
    turned round (`backward_start`) and takes the forward pass's modes of the frame after at each step
    (`feed_backward`)."""
    k = s.cfg.kjs
    if feed is not None:
        start, modes = frames[0], backward_start(feed[-1][0])
    else:
        seen = (s.problem.observations.confidence > 0).any(-1)
        start = next((t for t in frames if bool(seen[t])), frames[0]) if k.init == "tree" else frames[0]
        modes = first_modes(s, strategy, start)
    first = list(frames).index(start)  # the start's place in the pass: it and the frames before take its modes
    zero = torch.zeros(len(s.chains), dtype=torch.long, device=modes.q.device)
    out: list[tuple[Modes, Tensor]] = []
    for i, t in enumerate(progress(frames)):
        if i <= first:
            out.append((modes, zero))
            continue
        if feed is not None:
            modes, counts = track_step(s, t, feed_backward(s, modes, feed[t + 1][0]), strategy, generator, orders=True)
        else:
            modes, counts = track_step(s, t, modes, strategy, generator)
        out.append((modes, counts.to(modes.q.device)))
    return out


def _seed(generator: torch.Generator) -> int:
    """A seed for another generator, drawn from a copy of `generator` (which itself does not move on: the forward
    pass draws what it draws without a backward pass)."""
    copy = torch.Generator(generator.device)
    copy.set_state(generator.get_state())
    return int(torch.randint(0, 2**62, (1,), generator=copy, device=generator.device))


def _one_display(progress: Callable[[Iterable], Iterable], frames: int) -> Callable[[Iterable], Iterable]:
    """Two passes of `frames` frames each under one progress display: -> a `progress` whose first call yields the
    display's first `frames` items (the forward pass's frames), its second the rest (the backward pass's), to the
    display's end (where a bar closes)."""
    display = iter(progress([*range(frames), *range(frames - 1, -1, -1)]))
    parts = iter([itertools.islice(display, frames), display])
    return lambda items: next(parts)


def estimate_kjs(problem: Problem, cfg: KjsRunConfig, generator: torch.Generator, progress=lambda x: x) -> Estimate:
    """`method: kjs`: kinematic jump sampling with CSS diffusion."""
    return track(problem, cfg, generator, KJS, progress)


def estimate_css(problem: Problem, cfg: KjsRunConfig, generator: torch.Generator, progress=lambda x: x) -> Estimate:
    """`method: css`: covariance scaled sampling only, same hypothesis budget."""
    return track(problem, cfg, generator, CSS, progress)


def estimate_ss(problem: Problem, cfg: KjsRunConfig, generator: torch.Generator, progress=lambda x: x) -> Estimate:
    """`method: ss`: spherical sampling only, same hypothesis budget and core volume."""
    return track(problem, cfg, generator, SS, progress)
