"""The output-error fit shared by the delay, backlash and scope estimators (``rough_residuals``): what it
removes (the target's own smooth motion), what it recovers (a coupled Jacobian), and its ridge."""
import numpy as np

from targetlock.estimation.play import rough_residuals


def _high_pass(z: np.ndarray, span: int = 15) -> np.ndarray:
    """Reference: ``z`` (n, 2) less its centred moving average over ``span`` rows, shorter at the ends."""
    h = span // 2
    return np.array([z[i] - z[max(i - h, 0):i + h + 1].mean(axis=0) for i in range(len(z))])


def _motions(k: int, n: int, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return np.cumsum(rng.normal(0.0, 0.01, (k, n, 2)), axis=1)       # rad, k candidates' modelled motion


def test_a_target_moving_at_constant_velocity_drops_out_and_a_coupled_jacobian_is_recovered():
    n = 120
    p = _motions(3, n, 0)
    j_true = np.array([[-900.0, 120.0], [80.0, -700.0]])             # px/rad, with cross coupling
    velocity = np.array([3.0, -2.0])                                   # px per frame, the target's own
    x = p[0] @ j_true.T + np.arange(n)[:, None] * velocity
    fitted, rn, kept = rough_residuals(x, p, j_true)
    np.testing.assert_allclose(fitted[0], j_true, rtol=1e-9)
    assert rn[0].max() < 1e-9 and kept[0].all()
    assert np.median(rn[1:], axis=1).min() > 1.0                     # the others do not explain it


def test_the_fit_is_ridge_least_squares_towards_the_prior_on_the_kept_rows():
    """J = (G + λI)⁻¹ (Σ dp dxᵀ + λ J_priorᵀ), transposed, with G = Σ dp dpᵀ over the high-passed
    increments and λ = ridge · trace(G) / 2 (a window with little motion keeps the prior where it says
    nothing); fitted on all rows, then again on the rows within 3x the median residual; the rows kept
    are those of the final fit. Checked per candidate against numpy's solve, with noise and one outlier."""
    rng = np.random.default_rng(5)
    n, ridge = 90, 0.3
    p = _motions(4, n, 1)
    j_true = np.array([[600.0, -50.0], [30.0, 500.0]])
    prior = np.array([[400.0, 60.0], [-30.0, 400.0]])
    x = p[2] @ j_true.T + rng.normal(0.0, 0.5, (n, 2))
    x[40] += (60.0, 0.0)
    fitted, rn, kept = rough_residuals(x, p, prior, ridge=ridge)
    dx = _high_pass(np.diff(x, axis=0))
    dp = np.array([_high_pass(np.diff(m, axis=0)) for m in p])
    for c in range(p.shape[0]):
        w = np.ones((n - 1, 1))
        for _ in range(2):
            g = (dp[c] * w).T @ dp[c]
            lam = ridge * 0.5 * np.trace(g)
            expected = np.linalg.solve(g + lam * np.eye(2), (dp[c] * w).T @ dx + lam * prior.T).T
            residual = np.linalg.norm(dx - dp[c] @ expected.T, axis=1)
            w = (residual <= 3.0 * np.median(residual) + 1e-12)[:, None].astype(float)
        np.testing.assert_allclose(fitted[c], expected, rtol=1e-9, atol=1e-9)
        np.testing.assert_allclose(rn[c], residual, atol=1e-9)
        np.testing.assert_array_equal(kept[c], residual <= 3.0 * np.median(residual) + 1e-12)
    assert kept[2, 39] == 0 and kept[2, 40] == 0                       # the outlier's two increments
    assert np.abs(fitted[2] - j_true).max() < 0.35 * np.abs(j_true).max()   # pulled towards the prior only
