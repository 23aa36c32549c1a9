"""Benchmark ptrack's forward kinematics against pytorch-kinematics on the same skeleton.

Both libraries get the same CMU skeleton (ptrack reads the ASF; pytorch-kinematics builds a chain
from `Skeleton.to_urdf()`) and the same realistic poses (real AMC frames, repeated and slightly
perturbed to fill the batch). Before timing, the script checks that both give the same joint
positions (and the same pose gradients), so the timings compare equal work.

Measured per (batch, dtype, mode):
    forward           ptrack: sk.forward_kinematics(q) -> (B, J, 3)
                      pk:     chain.forward_kinematics_tensor(q) -> (F, B, 4, 4)
    forward+backward  the above, loss = sum of squared joint positions (pk: the J joint frames'
                      translations, [:, :, :3, 3]), gradient w.r.t. the pose q (B, D).
                      pk uses its default analytical backward.

Methodology: torch.set_num_threads(--threads), warm-up calls, then each measurement times enough
consecutive calls to take >= 0.2 s (time.perf_counter, torch.cuda.synchronize around it on CUDA);
the two libraries' measurements alternate, and the reported time per call is the median over the
repetitions. Ratio = pytorch-kinematics time / ptrack time (> 1: ptrack faster).

Usage (from the repo root, with ptrack installed or on the path):
    PYTHONPATH=. python scripts/bench_fk.py [--quick] [--threads N] [--device cuda] [--json out.json]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import sys
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass
from pathlib import Path

import pytorch_kinematics as pk
import torch
from _bench import machine_line

from ptrack.body.skeleton import Skeleton

REPO_ROOT = Path(__file__).resolve().parents[1]
DEFAULT_ASF = REPO_ROOT / ".." / "shared" / "data" / "cmu" / "subjects" / "64" / "64.asf"
DEFAULT_AMC = REPO_ROOT / ".." / "shared" / "data" / "cmu" / "subjects" / "64" / "64_01.amc"

BATCHES = (1, 64, 1024, 8192)
DTYPES = (torch.float32, torch.float64)
MODES = ("forward", "forward+backward")
MIN_MEASUREMENT_S = 0.2
WARMUP_CALLS = 3
CHECK_TOL_F32 = 1e-4  # metres


@dataclass(frozen=True)
class Row:
    """One benchmark cell: times are medians, milliseconds per call."""

    batch: int
    dtype: str
    mode: str
    ptrack_ms: float
    pk_ms: float
    ratio: float  # pk_ms / ptrack_ms
    ptrack_calls_per_measurement: int
    pk_calls_per_measurement: int
    ptrack_samples_ms: tuple[float, ...]
    pk_samples_ms: tuple[float, ...]


@dataclass(frozen=True)
class Check:
    """Agreement of the two libraries on the same poses."""

    dtype: str
    batch: int
    max_abs_joint_diff_m: float
    max_abs_grad_diff: float


@dataclass(frozen=True)
class Problem:
    """Everything one (dtype) needs: skeleton, chain, index maps, poses."""

    sk: Skeleton
    chain: pk.Chain
    perm: torch.Tensor  # (D,) chain dof k is ptrack dof perm[k]
    frame_idx: torch.Tensor  # (J,) chain frame of each ptrack joint


def build_problem(sk: Skeleton, urdf: bytes, dtype: torch.dtype, device: torch.device) -> Problem:
    chain = pk.build_chain_from_urdf(urdf).to(dtype=dtype, device=device)
    names = chain.get_joint_parameter_names()
    if sorted(names) != sorted(sk.dof_names):
        raise RuntimeError(f"chain dofs {names} do not match skeleton dofs {sk.dof_names}")
    perm = torch.tensor([sk.dof_names.index(n) for n in names], device=device)
    frame_idx = torch.tensor([chain.frame_to_idx[n] for n in sk.joint_names], device=device)
    return Problem(sk, chain, perm, frame_idx)


def make_poses(
    q_real: torch.Tensor, batch: int, dtype: torch.dtype, device: torch.device, gen: torch.Generator
) -> torch.Tensor:
    """Real frames cycled to fill the batch, each perturbed by N(0, 0.02) (rad / m): (B, D)."""
    idx = torch.arange(batch) % q_real.shape[0]
    noise = 0.02 * torch.randn(batch, q_real.shape[1], generator=gen, dtype=torch.float64)
    return (q_real[idx] + noise).to(dtype=dtype, device=device)


def ptrack_joints(pr: Problem, q: torch.Tensor) -> torch.Tensor:
    return pr.sk.forward_kinematics(q)  # (B, J, 3)


def pk_joints(pr: Problem, q_pk: torch.Tensor) -> torch.Tensor:
    t = pr.chain.forward_kinematics_tensor(q_pk)  # (F, B, 4, 4)
    return t[pr.frame_idx, :, :3, 3].transpose(0, 1)  # (B, J, 3)


def check_agreement(pr: Problem, q: torch.Tensor) -> Check:
    """Same joints and same d(sum of squared joints)/dq from both libraries."""
    q1 = q.detach().clone().requires_grad_(True)
    j1 = ptrack_joints(pr, q1)
    (g1,) = torch.autograd.grad(j1.square().sum(), q1)
    q2 = q.detach()[:, pr.perm].clone().requires_grad_(True)
    j2 = pk_joints(pr, q2)
    (g2,) = torch.autograd.grad(j2.square().sum(), q2)
    return Check(
        dtype=str(q.dtype).removeprefix("torch."),
        batch=q.shape[0],
        max_abs_joint_diff_m=float((j1 - j2).detach().abs().max()),
        max_abs_grad_diff=float((g1[:, pr.perm] - g2).abs().max()),
    )


def make_calls(pr: Problem, q: torch.Tensor, mode: str) -> tuple[Callable[[], object], Callable[[], object]]:
    """Zero-argument callables doing one ptrack call and one pk call of the given mode."""
    q_pt = q.detach().clone()
    q_pk = q.detach()[:, pr.perm].clone()
    if mode == "forward":
        return (lambda: ptrack_joints(pr, q_pt)), (lambda: pr.chain.forward_kinematics_tensor(q_pk))
    q_pt.requires_grad_(True)
    q_pk.requires_grad_(True)

    def pt_fb():
        return torch.autograd.grad(ptrack_joints(pr, q_pt).square().sum(), q_pt)[0]

    def pk_fb():
        t = pr.chain.forward_kinematics_tensor(q_pk)
        return torch.autograd.grad(t[pr.frame_idx, :, :3, 3].square().sum(), q_pk)[0]

    return pt_fb, pk_fb


def _timed(fn: Callable[[], object], n: int, sync: Callable[[], None]) -> float:
    """Seconds for n consecutive calls."""
    sync()
    t0 = time.perf_counter()
    for _ in range(n):
        fn()
    sync()
    return time.perf_counter() - t0


def _calibrate(fn: Callable[[], object], sync: Callable[[], None]) -> tuple[int, float]:
    """Calls per measurement so that one measurement takes >= MIN_MEASUREMENT_S; also that time."""
    n = 1
    while True:
        t = _timed(fn, n, sync)
        if t >= MIN_MEASUREMENT_S:
            return n, t
        n = max(2 * n, int(n * 1.2 * MIN_MEASUREMENT_S / max(t, 1e-9)) + 1)


def bench_pair(
    fa: Callable[[], object], fb: Callable[[], object], repeats: int, sync: Callable[[], None]
) -> tuple[tuple[int, list[float]], tuple[int, list[float]]]:
    """Alternating measurements of fa and fb: ((calls, [ms per call]), (calls, [ms per call]))."""
    for _ in range(WARMUP_CALLS):
        fa()
        fb()
    na, ta = _calibrate(fa, sync)
    nb, tb = _calibrate(fb, sync)
    sa, sb = [1e3 * ta / na], [1e3 * tb / nb]
    for _ in range(repeats - 1):
        sa.append(1e3 * _timed(fa, na, sync) / na)
        sb.append(1e3 * _timed(fb, nb, sync) / nb)
    return (na, sa), (nb, sb)


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--asf", type=Path, default=DEFAULT_ASF, help="ASF skeleton (default: CMU subject 64)")
    ap.add_argument("--amc", type=Path, default=DEFAULT_AMC, help="AMC motion giving the poses (default: 64_01)")
    ap.add_argument(
        "--threads",
        type=int,
        default=len(os.sched_getaffinity(0)),
        help="torch intra-op threads (default: all cores available to this process)",
    )
    ap.add_argument("--device", default="cpu", help="cpu or cuda (default: cpu)")
    ap.add_argument("--quick", action="store_true", help="3 repetitions per cell instead of 5")
    ap.add_argument("--json", type=Path, default=None, help="write the results to this JSON file")
    ap.add_argument("--seed", type=int, default=0, help="seed of the pose perturbations")
    args = ap.parse_args(argv)
    for p in (args.asf, args.amc):
        if not p.is_file():
            ap.error(f"file not found: {p}")
    if args.threads < 1:
        ap.error(f"--threads must be >= 1, got {args.threads}")
    if args.device.startswith("cuda") and not torch.cuda.is_available():
        ap.error("--device cuda requested but CUDA is not available")
    return args


def _ratio_phrase(r: float) -> str:
    if r >= 1.0:
        return f"ptrack is {r:.1f}x faster than pytorch-kinematics"
    return f"ptrack is {1.0 / r:.1f}x slower than pytorch-kinematics"


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    torch.set_num_threads(args.threads)
    device = torch.device(args.device)
    sync = (lambda: torch.cuda.synchronize(device)) if device.type == "cuda" else (lambda: None)
    repeats = 3 if args.quick else 5

    sk = Skeleton.from_asf(args.asf)
    q_real = sk.load_amc(args.amc).q  # (T, D) float64
    urdf = sk.to_urdf().encode()
    gen = torch.Generator().manual_seed(args.seed)
    poses = {b: make_poses(q_real, b, torch.float64, torch.device("cpu"), gen) for b in BATCHES}

    print(
        f"skeleton {sk.name!r} ({args.asf.name}): J={sk.num_joints} joints, D={sk.num_dofs} dofs; "
        f"poses: {q_real.shape[0]} frames of {args.amc.name}, cycled + N(0, 0.02) perturbation"
    )
    print(machine_line())
    print(
        f"torch {torch.__version__}, pytorch-kinematics {_pk_version()}, device {device}, "
        f"threads {torch.get_num_threads()}, {platform.processor() or platform.machine()}, "
        f"repeats {repeats}, >= {MIN_MEASUREMENT_S} s per measurement"
    )

    problems = {dt: build_problem(sk, urdf, dt, device) for dt in DTYPES}
    print(f"pytorch-kinematics chain: {problems[torch.float32].chain._num_frames} frames (4x4 each)")

    checks = []
    for dt in DTYPES:
        c = check_agreement(problems[dt], poses[1024].to(dtype=dt, device=device))
        checks.append(c)
        print(
            f"check {c.dtype}, batch {c.batch}: max |joints_ptrack - joints_pk| = {c.max_abs_joint_diff_m:.2e} m, "
            f"max |grad diff| = {c.max_abs_grad_diff:.2e}"
        )
    c32 = checks[0]
    if not c32.max_abs_joint_diff_m < CHECK_TOL_F32:
        print(
            f"FAILED: float32 joint difference {c32.max_abs_joint_diff_m:.2e} m >= {CHECK_TOL_F32:g} m; "
            "the libraries do not compute the same thing, timings would be meaningless",
            file=sys.stderr,
        )
        return 1

    header = f"{'batch':>6}  {'dtype':<8} {'mode':<17} {'ptrack ms':>11} {'pk ms':>11} {'pk/ptrack':>10}"
    print()
    print(header)
    print("-" * len(header))
    rows: list[Row] = []
    t_start = time.perf_counter()
    for b in BATCHES:
        for dt in DTYPES:
            pr = problems[dt]
            q = poses[b].to(dtype=dt, device=device)
            for mode in MODES:
                fa, fb = make_calls(pr, q, mode)
                (na, sa), (nb, sb) = bench_pair(fa, fb, repeats, sync)
                ma, mb = statistics.median(sa), statistics.median(sb)
                row = Row(b, str(dt).removeprefix("torch."), mode, ma, mb, mb / ma, na, nb, tuple(sa), tuple(sb))
                rows.append(row)
                print(f"{b:>6}  {row.dtype:<8} {mode:<17} {ma:>11.4f} {mb:>11.4f} {row.ratio:>9.2f}x", flush=True)
    elapsed = time.perf_counter() - t_start
    print("-" * len(header))

    def find(batch: int) -> Row:
        return next(r for r in rows if r.batch == batch and r.dtype == "float32" and r.mode == "forward")

    big, one = find(max(BATCHES)), find(1)
    print(f"timing took {elapsed:.0f} s")
    print(
        f"forward float32 batch {big.batch}: {_ratio_phrase(big.ratio)} "
        f"({big.ptrack_ms:.3f} ms vs {big.pk_ms:.3f} ms); "
        f"batch 1 forward float32 ratio: {one.ratio:.2f}x ({one.ptrack_ms:.3f} ms vs {one.pk_ms:.3f} ms)"
    )

    if args.json is not None:
        out = {
            "meta": {
                "torch": torch.__version__,
                "pytorch_kinematics": _pk_version(),
                "device": str(device),
                "threads": torch.get_num_threads(),
                "repeats": repeats,
                "min_measurement_s": MIN_MEASUREMENT_S,
                "asf": str(args.asf),
                "amc": str(args.amc),
                "joints": sk.num_joints,
                "dofs": sk.num_dofs,
                "pk_frames": problems[torch.float32].chain._num_frames,
                "seed": args.seed,
                "machine": platform.machine(),
                "python": platform.python_version(),
            },
            "checks": [asdict(c) for c in checks],
            "results": [asdict(r) for r in rows],
            "headline": {"batch": big.batch, "ratio": big.ratio, "batch1_ratio": one.ratio},
        }
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(out, indent=2))
        print(f"wrote {args.json}")
    return 0


def _pk_version() -> str:
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version("pytorch-kinematics")
    except PackageNotFoundError:
        return getattr(pk, "__version__", "unknown")


if __name__ == "__main__":
    raise SystemExit(main())
