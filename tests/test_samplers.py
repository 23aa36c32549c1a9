"""Tests for ptrack.hypotheses.samplers: the CSS covariance, CSS / SS proposals with Gaussian, Student-t and
Cauchy tails (statistical tests on fixed seeds), their log-densities, and projection onto limits."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from scipy import stats

from ptrack.errors import InputError
from ptrack.hypotheses.samplers import (
    Draws,
    css_proposal,
    project_to_limits,
    proposal_log_density,
    scaled_covariance,
    spherical_chol,
    spherical_proposal,
    spherical_std,
)

F64 = torch.float64
N_BIG = 200_000


def gen(seed: int = 0) -> torch.Generator:
    return torch.Generator().manual_seed(seed)


def ill_conditioned_hessian(seed: int = 0, K: int = 34, D: int = 50) -> torch.Tensor:
    """J^T J of a K x D Jacobian with column scales over 3 decades: rank K < D (D - K unobservable
    directions), the rest spread over ~6 decades of eigenvalues, like a monocular pose Hessian."""
    g = torch.Generator().manual_seed(seed)
    J = torch.randn(K, D, generator=g, dtype=F64) * torch.logspace(-1.5, 1.5, D, dtype=F64)
    return J.T @ J


def reference_covariance(H: torch.Tensor, scale: float, max_std: float) -> np.ndarray:
    """scale * H^-1 with H's eigenvalues floored at 1 / max_std^2, independently in numpy."""
    lam, V = np.linalg.eigh(H.numpy())
    return scale * (V / np.maximum(lam, 1.0 / max_std**2)) @ V.T


@pytest.fixture(scope="module")
def css50():
    """Hessian, reference covariance (scale 4, max_std 0.5) and its ScaledCovariance."""
    H = ill_conditioned_hessian()
    return H, reference_covariance(H, 4.0, 0.5), scaled_covariance(H, 4.0, max_std=0.5)


def whitened_error(samples: torch.Tensor, mean: torch.Tensor, sigma: np.ndarray) -> float:
    """|Sigma^-1/2 S Sigma^-1/2 - I|_F / sqrt(D): the sample covariance S relative to Sigma in every
    direction, the thin ones included (the plain Frobenius error only sees the wide ones)."""
    lam, V = np.linalg.eigh(sigma)
    w = V / np.sqrt(lam)
    y = (samples - mean).numpy() @ w
    S = y.T @ y / y.shape[0]
    return float(np.linalg.norm(S - np.eye(len(lam))) / math.sqrt(len(lam)))


# ---------------------------------------------------------------- scaled_covariance


def test_scaled_covariance_is_scale_times_inverse_hessian_where_observable():
    g = gen(1)
    A = torch.randn(6, 6, generator=g, dtype=F64)
    H = A @ A.T + 0.5 * torch.eye(6, dtype=F64)  # eigenvalues >= 0.5 > 1 / max_std^2
    sc = scaled_covariance(H, 8.0, max_std=10.0)
    torch.testing.assert_close(sc.covariance, 8.0 * torch.linalg.inv(H))
    torch.testing.assert_close(sc.chol @ sc.chol.mT, sc.covariance)
    assert torch.equal(sc.chol, torch.tril(sc.chol)) and bool((torch.diagonal(sc.chol) > 0).all())
    torch.testing.assert_close(sc.chol, torch.linalg.cholesky(sc.covariance))


def test_scaled_covariance_bounds_unobservable_and_stiff_directions(css50):
    H, ref, sc = css50
    np.testing.assert_allclose(sc.covariance.numpy(), ref, rtol=1e-9, atol=1e-12)
    lam = torch.linalg.eigvalsh(sc.covariance)
    assert lam.min() > 0 and lam.max() == pytest.approx(4.0 * 0.5**2)
    # the 16 directions J does not see get exactly std sqrt(scale) * max_std
    null = torch.linalg.eigh(H).eigenvectors[:, :16]
    torch.testing.assert_close(null.T @ sc.covariance @ null, 4.0 * 0.25 * torch.eye(16, dtype=F64))
    torch.testing.assert_close(sc.chol @ sc.chol.mT, sc.covariance, rtol=1e-9, atol=1e-12)
    # min_std: no direction narrower than sqrt(scale) * min_std
    lam2 = torch.linalg.eigvalsh(scaled_covariance(H, 4.0, max_std=0.5, min_std=0.05).covariance)
    assert lam2.min() == pytest.approx(4.0 * 0.05**2) and lam2.max() == pytest.approx(1.0)
    # round-off negative eigenvalues are unobservable directions, not errors
    Hneg = H - 1e-9 * torch.eye(50, dtype=F64)
    assert torch.linalg.eigvalsh(scaled_covariance(Hneg, 4.0, max_std=0.5).covariance).min() > 0


def test_scaled_covariance_batched_with_per_mode_scale():
    H = torch.stack([ill_conditioned_hessian(s, K=5, D=8) for s in range(3)])  # (3, 8, 8)
    scale = torch.tensor([1.0, 4.0, 16.0], dtype=F64)
    sc = scaled_covariance(H, scale, max_std=0.3)
    assert sc.covariance.shape == (3, 8, 8) and sc.chol.shape == (3, 8, 8)
    for m in range(3):
        one = scaled_covariance(H[m], float(scale[m]), max_std=0.3)
        torch.testing.assert_close(sc.covariance[m], one.covariance)
        torch.testing.assert_close(sc.chol[m], one.chol)
    deep = scaled_covariance(H.reshape(3, 1, 8, 8).expand(3, 2, 8, 8), 2.0)
    assert deep.covariance.shape == (3, 2, 8, 8)


def test_scaled_covariance_float32_follows_input(css50):
    H, ref, _ = css50
    sc = scaled_covariance(H.float(), 4.0, max_std=0.5)
    assert sc.covariance.dtype == torch.float32 and sc.chol.dtype == torch.float32
    # H rounded to float32 moves its small eigenvalues; the covariance still agrees to ~1e-4
    assert np.linalg.norm(sc.covariance.double().numpy() - ref) / np.linalg.norm(ref) < 1e-3
    torch.testing.assert_close(sc.chol @ sc.chol.mT, sc.covariance, rtol=1e-4, atol=1e-6)


def test_scaled_covariance_gradcheck():
    g = gen(2)
    A = torch.randn(4, 4, generator=g, dtype=F64)
    H = (A @ A.T + torch.diag(torch.tensor([0.0, 0.5, 1.0, 2.0], dtype=F64))).requires_grad_()
    torch.autograd.gradcheck(lambda h: scaled_covariance(h, 3.0, max_std=2.0), (H,))


# ---------------------------------------------------------------- CSS draws: the stated covariance


def test_css_gaussian_draws_have_the_stated_covariance(css50):
    """Done-when of the issue: 200k draws, fixed seed, covariance scale * H^-1 (regularised)."""
    _H, ref, sc = css50
    mean = torch.linspace(-1, 1, 50, dtype=F64)[None]
    d = css_proposal(mean, sc.chol[None], N_BIG, gen(0))
    x = d.samples[0]
    S = torch.cov(x.T).numpy()
    assert np.linalg.norm(S - ref) / np.linalg.norm(ref) < 0.02
    assert whitened_error(x, mean[0], ref) < 0.03
    assert (x.mean(0) - mean[0]).abs().max() < 5 * math.sqrt(4 * 0.25 / N_BIG)


def test_css_student_draws_have_covariance_dof_over_dof_minus_2(css50):
    _H, ref, sc = css50
    mean = torch.zeros(1, 50, dtype=F64)
    x = css_proposal(mean, sc.chol[None], N_BIG, gen(3), tail="student", dof=5.0).samples[0]
    S = torch.cov(x.T).numpy()
    target = 5.0 / 3.0 * ref
    assert np.linalg.norm(S - target) / np.linalg.norm(target) < 0.04
    assert whitened_error(x, mean[0], target) < 0.05


def test_css_cauchy_median_absolute_deviation_is_the_scale():
    """A Cauchy marginal with scale c has median |x - mean| = c; here c = sqrt(Sigma_ii)."""
    H = ill_conditioned_hessian(K=8, D=10)
    sc = scaled_covariance(H, 1.0, max_std=0.5)
    mean = torch.full((1, 10), 0.3, dtype=F64)
    d = css_proposal(mean, sc.chol[None], N_BIG, gen(4), tail="cauchy")
    mad = (d.samples[0] - mean).abs().median(0).values
    torch.testing.assert_close(mad, torch.diagonal(sc.covariance).sqrt(), rtol=0.02, atol=0)
    # whitened, every coordinate is standard Cauchy
    u = torch.linalg.solve_triangular(sc.chol, (d.samples[0] - mean).T, upper=False)
    torch.testing.assert_close(u.abs().median(1).values, torch.ones(10, dtype=F64), rtol=0.02, atol=0)
    assert torch.isfinite(d.samples).all() and torch.isfinite(d.log_density).all()


# ---------------------------------------------------------------- spherical sampling


def test_spherical_has_the_css_core_volume(css50):
    _, ref, sc = css50
    std = spherical_std(sc.chol)
    assert float(2 * 50 * std.log()) == pytest.approx(np.linalg.slogdet(ref)[1], rel=1e-10)
    L = spherical_chol(sc.chol[None])
    torch.testing.assert_close(torch.logdet(L[0] @ L[0].mT), torch.logdet(sc.covariance))
    mean = torch.zeros(1, 50, dtype=F64)
    ss = spherical_proposal(mean, sc.chol[None], N_BIG // 4, gen(5))
    S = torch.cov(ss.samples[0].T)
    torch.testing.assert_close(S, std**2 * torch.eye(50, dtype=F64), atol=0.03 * float(std**2), rtol=0)
    # same seed: SS and CSS share their draws, and equal volumes give equal log-densities
    css = css_proposal(mean, sc.chol[None], N_BIG // 4, gen(5))
    torch.testing.assert_close(ss.log_density, css.log_density)
    torch.testing.assert_close(ss.log_density, proposal_log_density(ss.samples, mean, L)[..., 0])


@pytest.mark.parametrize("tail,dof", [("student", 4.0), ("cauchy", None)])
def test_spherical_heavy_tails(tail, dof):
    chol = torch.diag(torch.tensor([0.1, 1.0, 10.0], dtype=F64))[None]  # det^(1/6) = 1
    d = spherical_proposal(torch.zeros(1, 3, dtype=F64), chol, N_BIG // 2, gen(6), tail=tail, dof=dof)
    if tail == "cauchy":
        torch.testing.assert_close(d.samples[0].abs().median(0).values, torch.ones(3, dtype=F64), rtol=0.03, atol=0)
    else:  # Student-t, scale I: covariance dof / (dof - 2) I = 2 I (dof = 4: loose, fourth moment infinite)
        torch.testing.assert_close(d.samples[0].var(0), torch.full((3,), 2.0, dtype=F64), rtol=0.1, atol=0)


# ---------------------------------------------------------------- log-density


def test_gaussian_log_density_matches_multivariate_normal():
    H = ill_conditioned_hessian(K=4, D=6)
    sc = scaled_covariance(torch.stack([H, H + torch.eye(6, dtype=F64)]), torch.tensor([4.0, 8.0], dtype=F64))
    mean = torch.randn(2, 6, generator=gen(7), dtype=F64)
    d = css_proposal(mean, sc.chol, 50, gen(8))
    mvn = torch.distributions.MultivariateNormal(mean[:, None], scale_tril=sc.chol[:, None])
    torch.testing.assert_close(d.log_density, mvn.log_prob(d.samples))
    # every point under every component
    lp = proposal_log_density(d.samples, mean, sc.chol)  # (2, 50, 2)
    assert lp.shape == (2, 50, 2)
    mvn_all = torch.distributions.MultivariateNormal(mean, scale_tril=sc.chol)
    torch.testing.assert_close(lp, mvn_all.log_prob(d.samples[..., None, :]))


def test_student_log_density_matches_torch_in_1d_and_scipy_in_nd():
    mean1, chol1 = torch.tensor([[0.4]], dtype=F64), torch.tensor([[[0.7]]], dtype=F64)
    d = css_proposal(mean1, chol1, 100, gen(9), tail="student", dof=3.0)
    ref = torch.distributions.StudentT(3.0, 0.4, 0.7).log_prob(d.samples[0, :, 0])
    torch.testing.assert_close(d.log_density[0], ref)
    H = ill_conditioned_hessian(K=5, D=5) + 0.1 * torch.eye(5, dtype=F64)
    sc = scaled_covariance(H, 2.0)
    mean = torch.randn(1, 5, generator=gen(10), dtype=F64)
    for tail, dof, df in (("student", 5.0, 5.0), ("cauchy", None, 1.0)):
        d = css_proposal(mean, sc.chol[None], 100, gen(11), tail=tail, dof=dof)
        ref = stats.multivariate_t(mean[0].numpy(), sc.covariance.numpy(), df=df).logpdf(d.samples[0].numpy())
        np.testing.assert_allclose(d.log_density[0].numpy(), ref, rtol=1e-10)
        torch.testing.assert_close(
            proposal_log_density(d.samples, mean, sc.chol[None], tail=tail, dof=dof)[..., 0], d.log_density
        )


def test_log_densities_integrate_to_one():
    """E_t[N(x) / t(x)] = integral of N = 1, with t the proposal's own density (heavier tails keep the
    estimator's variance finite): checks both normalisations at once."""
    sc = scaled_covariance(ill_conditioned_hessian(K=3, D=3) + 0.2 * torch.eye(3, dtype=F64), 1.0)
    mean = torch.tensor([[0.1, -0.2, 0.3]], dtype=F64)
    d = css_proposal(mean, sc.chol[None], N_BIG, gen(12), tail="student", dof=3.0)
    log_n = proposal_log_density(d.samples, mean, sc.chol[None])[..., 0]
    assert float(torch.exp(log_n - d.log_density).mean()) == pytest.approx(1.0, abs=0.01)


def test_proposal_log_density_gradcheck():
    g = gen(13)
    x = torch.randn(2, 3, 3, generator=g, dtype=F64, requires_grad=True)
    mean = torch.randn(2, 3, generator=g, dtype=F64, requires_grad=True)
    chol = (torch.tril(torch.randn(2, 3, 3, generator=g, dtype=F64), -1) + 2 * torch.eye(3, dtype=F64)).requires_grad_()
    for tail, dof in (("gaussian", None), ("student", 4.0)):
        torch.autograd.gradcheck(lambda a, b, c: proposal_log_density(a, b, c, tail=tail, dof=dof), (x, mean, chol))


def test_samples_are_reparameterised():
    mean = torch.zeros(2, 3, dtype=F64, requires_grad=True)
    chol = torch.eye(3, dtype=F64).repeat(2, 1, 1).requires_grad_()
    d = css_proposal(mean, chol, 5, gen(14))
    d.samples.sum().backward()
    torch.testing.assert_close(mean.grad, torch.full((2, 3), 5.0, dtype=F64))
    assert chol.grad is not None and torch.isfinite(chol.grad).all()


# ---------------------------------------------------------------- seeds, dtypes, devices, shapes


@pytest.mark.parametrize("tail,dof", [("gaussian", None), ("student", 5.0), ("cauchy", None)])
@pytest.mark.parametrize("sampler", [css_proposal, spherical_proposal])
def test_same_seed_same_samples(sampler, tail, dof):
    sc = scaled_covariance(ill_conditioned_hessian(K=4, D=6).expand(3, 6, 6), 4.0)
    mean = torch.randn(3, 6, generator=gen(15), dtype=F64)
    a = sampler(mean, sc.chol, 20, gen(1), tail=tail, dof=dof)
    b = sampler(mean, sc.chol, 20, gen(1), tail=tail, dof=dof)
    c = sampler(mean, sc.chol, 20, gen(2), tail=tail, dof=dof)
    assert torch.equal(a.samples, b.samples) and torch.equal(a.log_density, b.log_density)
    assert not torch.equal(a.samples, c.samples)
    # a generator carries on: a second call gives new samples
    g = gen(1)
    first, second = sampler(mean, sc.chol, 20, g, tail=tail, dof=dof), sampler(mean, sc.chol, 20, g, tail=tail, dof=dof)
    assert torch.equal(first.samples, a.samples) and not torch.equal(first.samples, second.samples)
    # float32: the same draws, rounded
    a32 = sampler(mean.float(), sc.chol.float(), 20, gen(1), tail=tail, dof=dof)
    assert a32.samples.dtype == torch.float32 and a32.log_density.dtype == torch.float32
    torch.testing.assert_close(a32.samples.double(), a.samples, rtol=1e-4, atol=1e-4)
    torch.testing.assert_close(a32.log_density.double(), a.log_density, rtol=1e-4, atol=1e-3)


def test_batched_shapes_and_counts():
    M, S, D = 3, 7, 4
    mean = torch.arange(M * D, dtype=F64).reshape(M, D)
    chol = 0.1 * torch.eye(D, dtype=F64).repeat(M, 1, 1)
    d = css_proposal(mean, chol, S, gen(16))
    assert isinstance(d, Draws)
    assert d.samples.shape == (M, S, D) and d.log_density.shape == (M, S) and d.component.shape == (M, S)
    assert torch.equal(d.component, torch.arange(M)[:, None].expand(M, S))
    # per-mode counts: flat, mode-major
    f = css_proposal(mean, chol, torch.tensor([S, 0, 2]), gen(16))
    assert f.samples.shape == (S + 2, D) and f.log_density.shape == (S + 2,)
    assert f.component.tolist() == [0] * S + [2, 2]
    assert ((f.samples - mean[f.component]).abs() < 1.0).all()  # each around its own mode
    # equal counts give the uniform layout's draws, flattened
    e = css_proposal(mean, chol, [S] * M, gen(16))
    assert torch.equal(e.samples, d.samples.reshape(M * S, D)) and torch.equal(e.component, d.component.flatten())
    torch.testing.assert_close(
        f.log_density, proposal_log_density(f.samples[:, None], mean, chol)[torch.arange(S + 2), 0, f.component]
    )
    assert css_proposal(mean, chol, [0, 0, 0], gen(0)).samples.shape == (0, D)
    assert spherical_proposal(mean, chol, 0, gen(0)).samples.shape == (M, 0, D)
    assert proposal_log_density(torch.zeros(5, 2, D, dtype=F64), mean, chol).shape == (5, 2, M)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_cpu_generator_with_cuda_tensors():
    sc = scaled_covariance(ill_conditioned_hessian(K=4, D=6)[None], 4.0)
    mean = torch.zeros(1, 6, dtype=F64)
    cpu = css_proposal(mean, sc.chol, 10, gen(1), tail="student", dof=5.0)
    cuda = css_proposal(mean.cuda(), sc.chol.cuda(), 10, gen(1), tail="student", dof=5.0)
    assert cuda.samples.device.type == "cuda"
    torch.testing.assert_close(cuda.samples.cpu(), cpu.samples)


# ---------------------------------------------------------------- projection onto limits


LOWER = torch.tensor([-1.0, 0.0, -math.inf, -math.inf, 0.5, 2.0], dtype=F64)
UPPER = torch.tensor([1.0, math.inf, 0.0, math.inf, 0.5, 3.0], dtype=F64)


@pytest.mark.parametrize("mode", ["clamp", "reflect"])
def test_projection_keeps_samples_within_limits_and_inside_ones_untouched(mode):
    q = 3.0 * torch.randn(2000, 6, generator=gen(17), dtype=F64)
    p = project_to_limits(q, LOWER, UPPER, mode=mode)
    assert p.shape == q.shape and p.dtype == q.dtype
    assert bool(((p >= LOWER) & (p <= UPPER)).all())
    inside = (q >= LOWER) & (q <= UPPER)
    assert inside.any() and torch.equal(p[inside], q[inside])
    assert torch.equal(p[:, 3], q[:, 3])  # unlimited
    p32 = project_to_limits(q.float().reshape(40, 50, 6), LOWER, UPPER, mode=mode)
    assert p32.dtype == torch.float32 and p32.shape == (40, 50, 6)
    torch.testing.assert_close(p32.reshape(2000, 6).double(), p, rtol=0, atol=1e-5)


def test_clamp_and_reflect_values():
    q = torch.tensor([[1.25, -0.5, 0.75, 9.0, 0.6, 3.5], [-3.5, 2.0, -1.0, -9.0, 0.4, 6.5]], dtype=F64)
    clamped = project_to_limits(q, LOWER, UPPER)
    torch.testing.assert_close(
        clamped, torch.tensor([[1.0, 0.0, 0.0, 9.0, 0.5, 3.0], [-1.0, 2.0, -1.0, -9.0, 0.5, 3.0]], dtype=F64)
    )
    reflected = project_to_limits(q, LOWER, UPPER, mode="reflect")
    # 1.25 -> 0.75; -3.5 folds off both walls of [-1, 1] -> 0.5; one-sided walls mirror; zero width
    # -> the bound; 6.5 in [2, 3] folds to 2.5
    torch.testing.assert_close(
        reflected, torch.tensor([[0.75, 0.5, -0.75, 9.0, 0.5, 2.5], [0.5, 2.0, -1.0, -9.0, 0.5, 2.5]], dtype=F64)
    )
    for mode in ("clamp", "reflect"):
        nan = project_to_limits(torch.full((1, 6), math.nan, dtype=F64), LOWER, UPPER, mode=mode)
        assert torch.isnan(nan).all()
        inf = project_to_limits(torch.tensor([[math.inf] * 6, [-math.inf] * 6], dtype=F64), LOWER, UPPER, mode=mode)
        torch.testing.assert_close(
            inf,
            torch.stack([torch.minimum(UPPER, torch.tensor(math.inf)), torch.maximum(LOWER, torch.tensor(-math.inf))]),
        )


def test_reflect_does_not_pile_samples_on_the_boundary():
    q = torch.randn(10000, 1, generator=gen(18), dtype=F64)
    lo, hi = torch.tensor([-0.5], dtype=F64), torch.tensor([0.5], dtype=F64)
    assert (project_to_limits(q, lo, hi).abs() == 0.5).float().mean() > 0.5
    r = project_to_limits(q, lo, hi, mode="reflect")
    assert (r.abs() == 0.5).sum() == 0
    hist = torch.histc(r, bins=10, min=-0.5, max=0.5)
    assert hist.max() / hist.min() < 1.3  # folding N(0, 1) into [-0.5, 0.5] is nearly flat


@pytest.mark.parametrize("mode", ["clamp", "reflect"])
def test_projection_wraps_angles_into_their_arc_first(mode):
    tau = 2 * math.pi
    lower = torch.tensor([2.5, -1.0, -math.inf], dtype=F64)  # an arc across +-pi; a plain arc; unlimited
    upper = torch.tensor([3.5, 1.0, math.inf], dtype=F64)
    angular = torch.tensor([True, True, True])
    q = torch.tensor(
        [
            [-3.0, 0.5 + tau, 7.0],  # -3.0 is 3.28 on the circle: inside [2.5, 3.5]
            [-2.6, -1.1 - tau, -7.0],
        ],
        dtype=F64,
    )  # -2.6 is 3.68: 0.18 past 3.5
    p = project_to_limits(q, lower, upper, angular, mode=mode)
    assert p[0, 0] == pytest.approx(-3.0 + tau) and p[0, 1] == pytest.approx(0.5)
    assert p[0, 2] == 7.0 and p[1, 2] == -7.0
    over = 3.5 if mode == "clamp" else 3.5 - (-2.6 + tau - 3.5)
    under = -1.0 if mode == "clamp" else -0.9
    assert p[1, 0] == pytest.approx(over) and p[1, 1] == pytest.approx(under)
    # a translation (not angular) 2 pi away is not wrapped
    lin = project_to_limits(q[:, :2], lower[:2], upper[:2], torch.tensor([False, False]), mode=mode)
    assert bool(((lin >= lower[:2]) & (lin <= upper[:2])).all()) and lin[0, 1] != pytest.approx(0.5)


# ---------------------------------------------------------------- errors


def test_input_errors():
    H = torch.eye(3, dtype=F64)
    mean, chol = torch.zeros(2, 3, dtype=F64), torch.eye(3, dtype=F64).repeat(2, 1, 1)
    for bad in (0.0, -1.0, math.nan, math.inf, torch.tensor([1.0, 0.0], dtype=F64)):
        with pytest.raises(InputError, match="scale"):
            scaled_covariance(H.expand(2, 3, 3), bad)
    with pytest.raises(InputError, match="scale"):
        scaled_covariance(H.expand(2, 3, 3), torch.ones(3))
    with pytest.raises(InputError, match="hessian"):
        scaled_covariance(torch.zeros(3, 4), 1.0)
    with pytest.raises(InputError, match="non-finite"):
        scaled_covariance(torch.full((3, 3), math.nan), 1.0)
    with pytest.raises(InputError, match="max_std"):
        scaled_covariance(H, 1.0, max_std=0.0)
    with pytest.raises(InputError, match="min_std"):
        scaled_covariance(H, 1.0, max_std=1.0, min_std=2.0)
    for sampler in (css_proposal, spherical_proposal):
        with pytest.raises(InputError, match="tail"):
            sampler(mean, chol, 4, gen(), tail="laplace")
        for dof in (0.0, -2.0, math.inf):
            with pytest.raises(InputError, match="dof"):
                sampler(mean, chol, 4, gen(), tail="student", dof=dof)
        with pytest.raises(InputError, match="dof"):
            sampler(mean, chol, 4, gen(), tail="student")
        with pytest.raises(InputError, match="chol"):
            sampler(mean, chol[:, :2, :2], 4, gen())
        with pytest.raises(InputError, match="mean"):
            sampler(mean[0], chol, 4, gen())
        with pytest.raises(InputError, match="counts"):
            sampler(mean, chol, [1, 2, 3], gen())
        with pytest.raises(InputError, match="counts"):
            sampler(mean, chol, [1, -2], gen())
        with pytest.raises(InputError, match="counts"):
            sampler(mean, chol, torch.tensor([1.5, 2.0]), gen())
        with pytest.raises(InputError, match="n "):
            sampler(mean, chol, -1, gen())
        with pytest.raises(InputError, match="generator"):
            sampler(mean, chol, 4, 0)
    with pytest.raises(InputError, match="x must"):
        proposal_log_density(torch.zeros(5, 4, dtype=F64), mean, chol)
    with pytest.raises(InputError, match="tail"):
        proposal_log_density(torch.zeros(5, 3, dtype=F64), mean, chol, tail="t")
    q = torch.zeros(4, 6, dtype=F64)
    with pytest.raises(InputError, match="lower"):
        project_to_limits(q, LOWER[:5], UPPER)
    with pytest.raises(InputError, match="upper"):
        project_to_limits(q, LOWER, UPPER[:5])
    with pytest.raises(InputError, match="lower must be <= upper"):
        project_to_limits(q, UPPER, LOWER)
    with pytest.raises(InputError, match="angular"):
        project_to_limits(q, LOWER, UPPER, torch.ones(6))
    with pytest.raises(InputError, match="projection mode"):
        project_to_limits(q, LOWER, UPPER, mode="wrap")
