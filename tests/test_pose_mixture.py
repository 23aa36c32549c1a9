"""The CMU pose mixture (`ptrack.body.pose_mixture`): the shipped file, its density on a skeleton (marginalised,
wrapped), that it knows which angles go together, and its place in the kjs tracker's frame cost."""

from __future__ import annotations

import json
import math
from pathlib import Path

import pytest
import torch

from ptrack.body.pose_mixture import pose_mixture, pose_mixture_path, read_pose_mixture
from ptrack.body.pose_prior import pose_prior
from ptrack.body.skeleton import Skeleton, load_amc
from ptrack.clips import parse_clips
from ptrack.errors import InputError
from ptrack.estimators.kjs import KJS
from ptrack.estimators.kjs.model import frame_evidence, make_setup
from ptrack.pipeline.config import load_config
from ptrack.pipeline.run import prepare

REPO = Path(__file__).resolve().parents[1]
DATA = REPO / "ptrack" / "data"


@pytest.fixture(scope="module")
def full():
    return Skeleton.from_asf(DATA / "10.asf").with_limits("data")


def _direct_nll(table, names, q):
    """-log sum_c w_c N(wrap(q - mu_c); 0, cov_c) on the dofs `names`, with torch.distributions."""
    idx = [table.dofs.index(n) for n in names]
    dens = []
    for w, mu, cov in zip(table.weights, table.means, table.covariances):
        d = torch.remainder(q - mu[idx] + math.pi, 2 * math.pi) - math.pi
        mvn = torch.distributions.MultivariateNormal(torch.zeros(len(idx), dtype=q.dtype), cov[idx][:, idx])
        dens.append(math.log(float(w)) + mvn.log_prob(d))
    return -torch.logsumexp(torch.stack(dens, -1), -1)


def test_shipped_file_holds_out_the_judged_clips():
    """Fitted to no held-out clip and no check clip of the synthetic footage; on every non-root CMU dof; a proper
    mixture (weights summing to 1, covariances positive definite)."""
    doc = json.loads(pose_mixture_path().read_text())
    held = {p.stem for p in parse_clips(str(REPO / "configs" / "clips" / "heldout_batch.txt"))}
    check = {"07_05", "35_01", "02_05", "49_19", "135_04"}  # scripts/eval_synthetic_footage.py's check group
    assert doc["clips"] and not set(doc["clips"]) & (held | check)
    table = read_pose_mixture()
    sk = Skeleton.from_asf(DATA / "10.asf")
    assert set(table.dofs) == {n for n in sk.dof_names if not n.startswith("root.")}
    assert float(table.weights.sum()) == pytest.approx(1.0, abs=1e-9)
    assert bool((torch.linalg.eigvalsh(table.covariances) > 0).all())


def test_density_marginalised_onto_the_skeletons_dofs(full):
    """On the full CMU skeleton and on one with frozen hands, fingers and toes: the density of each component's
    covariance block of the dofs the skeleton has (a Gaussian's marginal), root dofs ignored."""
    table = read_pose_mixture()
    q_full = load_amc(DATA / "10_02.amc", full).q[::40].double()
    for sk in (full, full.freeze(["*fingers", "*thumb", "*hand", "*toes"])):
        q = sk.reduce(q_full, full)
        mix = pose_mixture(sk, torch.float64, torch.device("cpu"))
        names = [n for n in sk.dof_names if n in table.dofs]
        cols = [sk.dof_names.index(n) for n in names]
        assert mix.index.tolist() == cols
        expected = _direct_nll(table, names, q[:, cols])
        assert torch.allclose(mix.nll(q), expected, rtol=1e-9, atol=1e-9)
        shifted = q.clone()
        shifted[:, cols[0]] += 2 * math.pi  # a whole turn is the same angle
        shifted[:, :6] += 0.7  # the root (heading, position) is not in the mixture
        assert torch.allclose(mix.nll(shifted), mix.nll(q), rtol=1e-9, atol=1e-9)


@pytest.mark.parametrize("clip, least", [("35_01", 0.7), ("49_19", 0.9)])
def test_it_knows_which_angles_go_together(cmu_file, clip, least):
    """On clips it was not fitted to (a walk, a one-leg balance), real poses cost less than poses with the same
    per-dof angles recombined across frames (each dof from another random frame): the per-dof prior cannot tell
    the two sets apart (each dof's values are the same), the mixture ranks the real pose first in most frames
    (measured over five shuffles: 0.78-0.82 of the walk's frames, 0.98-1.00 of the balance's)."""
    subject = clip.split("_")[0]
    sk = Skeleton.from_asf(cmu_file(f"{subject}.asf")).with_limits("data")
    q = load_amc(cmu_file(f"{clip}.amc"), sk).q[::4].double()
    mix = pose_mixture(sk, torch.float64, torch.device("cpu"))
    g = torch.Generator().manual_seed(0)
    shuffled = torch.stack([q[torch.randperm(q.shape[0], generator=g), d] for d in range(q.shape[1])], -1)
    lower, upper = sk.limits(dtype=torch.float64)
    mean, std, known = pose_prior(sk, lower, upper, torch.as_tensor(sk.angular_dofs()))

    def per_dof(x):
        d = torch.remainder(x - mean + math.pi, 2 * math.pi) - math.pi
        return (0.5 * (d / std.clamp_min(1e-6)).square() * known).sum(-1)

    assert float(per_dof(q).sum()) == pytest.approx(float(per_dof(shuffled).sum()), rel=1e-9)
    share = float((mix.nll(q) < mix.nll(shuffled)).double().mean())
    assert share > least, share


def test_frame_evidence_adds_the_weighted_mixture():
    """`kjs.pose_mixture_weight` w: each mode's frame cost gains w times the mixture's negative log-density; 0 (the
    default of configs/kjs.yaml) leaves it as it was."""
    base = load_config(REPO / "configs" / "kjs.yaml", ["data.stop=12", "progress=false"])
    assert base.kjs.pose_mixture_weight == 0
    prep = prepare(base)
    plain = make_setup(prep.problem, base, KJS)
    assert plain.mixture is None
    cfg = load_config(REPO / "configs" / "kjs.yaml", ["data.stop=12", "progress=false", "kjs.pose_mixture_weight=2.5"])
    s = make_setup(prep.problem, cfg, KJS)
    q = prep.gt_q[:3].to(prep.problem.observations.keypoints)
    t = torch.arange(3)
    expected = frame_evidence(plain, t, q) + 2.5 * s.mixture.nll(q)
    assert torch.allclose(frame_evidence(s, t, q), expected, rtol=1e-5, atol=1e-3)


def test_needs_cmu_dof_names():
    """A skeleton that names none of the mixture's dofs gets one error naming the key."""

    class Other:
        dof_names = ("root.tx", "knee.flex")

    assert pose_mixture(Other(), torch.float32, torch.device("cpu")) is None
    from ptrack.estimators.kjs.model import _mixture

    with pytest.raises(InputError, match=r"kjs\.pose_mixture_weight"):
        _mixture(Other(), 1.0, torch.float32, torch.device("cpu"))
    assert _mixture(Other(), 0.0, torch.float32, torch.device("cpu")) is None


def test_bad_files(tmp_path):
    with pytest.raises(FileNotFoundError):
        read_pose_mixture(tmp_path / "none.json")
    bad = tmp_path / "bad.json"
    bad.write_text('{"dofs": ["a", "b"], "weights": [1.0], "means": [[0, 0]], "covariances": [[1, 0]]}')
    with pytest.raises(InputError, match="lower triangles"):
        read_pose_mixture(bad)
    bad.write_text("{}")
    with pytest.raises(InputError, match="must be JSON"):
        read_pose_mixture(bad)
