"""Make `ptrack/data/cmu_pose_mixture.json`: the Gaussian mixture over joint angles of `ptrack.body.pose_mixture`.

    python scripts/make_pose_mixture.py [--cmu ../shared/data/cmu] [--components 4] [--stride 4] [--seed 0]
                                        [--exclude-clips configs/clips/heldout_batch.txt] [--out FILE]

The clips: every AMC clip under `--cmu` less the held-out clips of `--exclude-clips` and the check clips of
`scripts/eval_synthetic_footage.py` (its `check` group), so that neither is judged with a prior fitted to it;
every `--stride`-th frame (120 fps -> 30 fps), the non-root dofs of the CMU skeleton, each angle wrapped into
[-pi, pi). Unlike the per-dof prior (`scripts/make_pose_prior.py`) the development clips' subjects are kept: the
mixture is a prior for real footage (`configs/video.yaml`), judged on the Pose2Sim trial and on the check clips,
and 13 clips (7 of them golf swings) are too few to say which angles go together. The mixture is fitted by
expectation-maximisation (k-means++ centres, `--iterations` EM steps, every covariance regularised by `REG_DEG`^2
on its diagonal), seeded, so the same clips give the same file. 4 components: on the Pose2Sim trial 4, 8 and 16
measured alike when they ranked the kjs tracker's modes (docs/notes/footage-history.md).
"""

from __future__ import annotations

import argparse
import json
import math
from datetime import date
from pathlib import Path

import numpy as np
from eval_synthetic_footage import GROUPS
from make_limits import load_clips

from ptrack.clips import parse_clips

ROOT = Path(__file__).resolve().parents[1]
#: the std (degrees) added to every covariance's diagonal: no component collapses onto a dof that a few
#: training clips hold still
REG_DEG = 2.0


def wrap(x: np.ndarray) -> np.ndarray:
    """Angles -> [-pi, pi)."""
    return np.remainder(x + math.pi, 2 * math.pi) - math.pi


def log_densities(x: np.ndarray, w: np.ndarray, mu: np.ndarray, cov: np.ndarray) -> np.ndarray:
    """x (N, D), weights (C,), means (C, D), covariances (C, D, D) -> log w_c N(x; mu_c, cov_c) (N, C), the
    differences wrapped (angles)."""
    out = np.empty((x.shape[0], len(w)))
    for c in range(len(w)):
        chol = np.linalg.cholesky(cov[c])
        z = np.linalg.solve(chol, wrap(x - mu[c]).T)  # (D, N)
        half_logdet = np.log(np.diag(chol)).sum()
        out[:, c] = math.log(w[c]) - 0.5 * (z * z).sum(0) - half_logdet - 0.5 * x.shape[1] * math.log(2 * math.pi)
    return out


def fit(x: np.ndarray, components: int, iterations: int, rng: np.random.Generator):
    """EM for a full-covariance Gaussian mixture on angles x (N, D) -> weights (C,), means (C, D), covariances
    (C, D, D), mean log-likelihood per frame. Means are circular means of the members' angles."""
    n, d = x.shape
    centres = [x[rng.integers(n)]]  # k-means++
    for _ in range(components - 1):
        gap = np.min([(wrap(x - c) ** 2).sum(1) for c in centres], axis=0)
        centres.append(x[rng.choice(n, p=gap / gap.sum())])
    mu = np.array(centres)
    reg = math.radians(REG_DEG) ** 2 * np.eye(d)
    cov = np.array([np.cov(wrap(x - m).T) + reg for m in mu])
    w = np.full(components, 1.0 / components)
    ll = -math.inf
    for _ in range(iterations):
        logp = log_densities(x, w, mu, cov)
        top = logp.max(1, keepdims=True)
        norm = top + np.log(np.exp(logp - top).sum(1, keepdims=True))
        ll = float(norm.mean())
        r = np.exp(logp - norm)  # (N, C) responsibilities
        nk = r.sum(0) + 1e-9
        w = nk / n
        mu = np.arctan2(r.T @ np.sin(x), r.T @ np.cos(x))
        for c in range(components):
            dx = wrap(x - mu[c])
            cov[c] = (r[:, c, None] * dx).T @ dx / nk[c] + reg
    return w, mu, cov, ll


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--cmu", default=str(ROOT / ".." / "shared" / "data" / "cmu"), help="CMU data folder")
    ap.add_argument("--exclude-clips", default=str(ROOT / "configs" / "clips" / "heldout_batch.txt"))
    ap.add_argument("--components", type=int, default=4)
    ap.add_argument("--iterations", type=int, default=100)
    ap.add_argument("--stride", type=int, default=4, help="frame stride")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", default=str(ROOT / "ptrack" / "data" / "cmu_pose_mixture.json"))
    args = ap.parse_args()
    sk, clips = load_clips(Path(args.cmu).resolve())
    left_out = {p.stem for p in parse_clips(args.exclude_clips)} | set(GROUPS["check"])
    used = {n: q[:: args.stride] for n, (_, q) in clips.items() if n not in left_out}
    if not used:
        raise SystemExit("every clip is excluded")
    dofs = [i for i, name in enumerate(sk.dof_names) if not name.startswith("root.")]
    x = wrap(np.concatenate(list(used.values()))[:, dofs])
    w, mu, cov, ll = fit(x, args.components, args.iterations, np.random.default_rng(args.seed))
    tril = np.tril_indices(len(dofs))
    doc = {
        "description": "Gaussian mixture over the non-root joint angles of the CMU skeleton (radians); "
        "covariances as their lower triangles, row by row; made by scripts/make_pose_mixture.py",
        "made": date.today().isoformat(),
        "clips": sorted(used),
        "frames": int(x.shape[0]),
        "stride": args.stride,
        "mean_log_likelihood": round(ll, 4),
        "dofs": [sk.dof_names[i] for i in dofs],
        "weights": [round(float(v), 8) for v in w],
        "means": [[round(float(v), 6) for v in m] for m in mu],
        "covariances": [[float(f"{v:.6g}") for v in c[tril]] for c in cov],
    }
    Path(args.out).write_text(json.dumps(doc, indent=None, separators=(",", ":")) + "\n", encoding="utf-8")
    print(f"{args.out}: {args.components} components, {x.shape[0]} frames of {len(used)} clips, mean log-lik {ll:.2f}")


if __name__ == "__main__":
    main()
