"""GP regression: agreement with scikit-learn, LML gradient, and hyperparameter recovery."""

from __future__ import annotations

import numpy as np
import pytest

from mapping.gp import GaussianProcess, GPHyperparameters, MaternKernel, fit_hyperparameters, log_marginal_likelihood


@pytest.fixture(autouse=True)
def single_blas_thread():
    """Batched small LAPACK calls thrash with several BLAS threads on the shared 2-core machine."""
    from threadpoolctl import threadpool_limits

    with threadpool_limits(1):
        yield


@pytest.mark.parametrize("nu", [1.5, 2.5, 3.5])
def test_matches_sklearn(nu, rng):
    """Mean and latent variance equal sklearn's GaussianProcessRegressor (same Matérn, alpha=σn²) to 1e-8."""
    from sklearn.gaussian_process import GaussianProcessRegressor
    from sklearn.gaussian_process.kernels import ConstantKernel, Matern

    X = rng.uniform(-3, 3, (120, 2))
    y = np.sign(rng.normal(size=120)) + 0.1 * rng.normal(size=120)
    Xs = rng.uniform(-4, 4, (300, 2))
    hyp = GPHyperparameters(nu=nu, length_scale=0.9, sigma_f=1.7, sigma_n=0.3)
    gp = GaussianProcess(hyp).fit(X, y)
    mu, var = gp.predict(Xs)
    kern = ConstantKernel(hyp.sigma_f**2, "fixed") * Matern(hyp.length_scale, "fixed", nu=nu)
    sk = GaussianProcessRegressor(kern, alpha=hyp.sigma_n**2, optimizer=None).fit(X, y)
    mu_s, std_s = sk.predict(Xs, return_std=True)
    np.testing.assert_allclose(mu, mu_s, atol=1e-8)
    np.testing.assert_allclose(var, std_s**2, atol=1e-8)


@pytest.mark.parametrize("nu", [1.5, 2.5, 3.5])
def test_lml_gradient_matches_finite_differences(nu, rng):
    """The analytic LML gradient equals central finite differences in log-parameter space."""
    X = rng.uniform(0, 4, (60, 2))
    y = rng.normal(size=60)
    hyp = GPHyperparameters(nu=nu, length_scale=0.8, sigma_f=1.2, sigma_n=0.4)
    _, g = log_marginal_likelihood(hyp, X, y)
    th = hyp.log_params()
    num = np.zeros(3)
    for i in range(3):
        e = np.zeros(3)
        e[i] = 1e-6
        lp = log_marginal_likelihood(GPHyperparameters.from_log(nu, th + e), X, y)[0]
        lm = log_marginal_likelihood(GPHyperparameters.from_log(nu, th - e), X, y)[0]
        num[i] = (lp - lm) / 2e-6
    np.testing.assert_allclose(g, num, rtol=1e-5, atol=1e-6)


def test_lml_matches_sklearn(rng):
    """The log marginal likelihood equals sklearn's for the same kernel and noise."""
    from sklearn.gaussian_process import GaussianProcessRegressor
    from sklearn.gaussian_process.kernels import ConstantKernel, Matern

    X = rng.uniform(0, 4, (80, 2))
    y = rng.normal(size=80)
    hyp = GPHyperparameters(nu=2.5, length_scale=0.7, sigma_f=1.1, sigma_n=0.2)
    kern = ConstantKernel(hyp.sigma_f**2, "fixed") * Matern(hyp.length_scale, "fixed", nu=2.5)
    sk = GaussianProcessRegressor(kern, alpha=hyp.sigma_n**2, optimizer=None).fit(X, y)
    assert log_marginal_likelihood(hyp, X, y)[0] == pytest.approx(sk.log_marginal_likelihood_value_, abs=1e-8)


def test_fit_recovers_length_scale():
    """Hyperparameters fitted to a sample drawn from a known GP recover ℓ, σf, σn within ~25 %."""
    rng = np.random.default_rng(7)
    true = GPHyperparameters(nu=3.5, length_scale=0.6, sigma_f=1.5, sigma_n=0.1)
    X = rng.uniform(0, 6, (400, 2))
    K = true.kernel(X) + 1e-9 * np.eye(len(X))
    f = np.linalg.cholesky(K) @ rng.normal(size=len(X))
    y = f + true.sigma_n * rng.normal(size=len(X))
    fit = fit_hyperparameters(X, y, GPHyperparameters(nu=3.5, length_scale=2.0, sigma_f=0.5, sigma_n=0.5), restarts=0)
    assert fit.length_scale == pytest.approx(0.6, rel=0.2)
    assert fit.sigma_n == pytest.approx(0.1, rel=0.25)
    assert fit.sigma_f == pytest.approx(1.5, rel=0.5)


def test_kernel_cutoff_is_tail_bound():
    """Beyond cutoff(tol) the kernel is below tol·σf² and just inside it is above."""
    k = MaternKernel(3.5, 1.9, 8.13)
    c = k.cutoff(1e-6)
    assert k.of_distance(np.array(c * 1.001)) < 1e-6 * k.variance < k.of_distance(np.array(c * 0.99))


@pytest.mark.parametrize("nu", [1.5, 2.5, 3.5])
def test_inplace_kernel_equals_kernel(nu, rng):
    """The in-place Horner evaluation used on hot paths equals the reference kernel formula."""
    k = MaternKernel(nu, 0.7, 2.3)
    r = rng.uniform(0, 5, 1000)
    np.testing.assert_allclose(k.of_distance_inplace(r.copy()), k.of_distance(r), rtol=1e-13, atol=1e-15)
