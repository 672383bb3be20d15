"""Known-answer tests for FID, KID, precision/recall and diversity (modi.evaluation.distribution)."""
from __future__ import annotations

import numpy as np
import pytest
from scipy import linalg, special

from modi.evaluation.distribution import (
    distribution_metrics,
    diversity,
    frechet_distance,
    kernel_distance,
    precision_recall,
)


def _gauss(n: int, d: int = 8, shift: float = 0.0, scale: float = 1.0, seed: int = 0) -> np.ndarray:
    return np.random.default_rng(seed).normal(size=(n, d)) * scale + shift


def test_fid_of_a_set_against_itself_is_zero():
    a = _gauss(500)
    assert frechet_distance(a, a) == pytest.approx(0.0, abs=1e-8)


def test_fid_matches_closed_form_for_diagonal_gaussians():
    # FID between empirical fits equals |dmu|^2 + sum (sqrt(va) - sqrt(vb))^2 when covariances are diagonal;
    # build two sets whose sample covariances are exactly diagonal (whitened, then scaled).
    rng = np.random.default_rng(1)
    z = rng.normal(size=(400, 3))
    z -= z.mean(0)
    z = z @ np.linalg.inv(np.linalg.cholesky(np.cov(z, rowvar=False))).T  # sample cov = I exactly
    a = z * np.array([1.0, 2.0, 0.5]) + np.array([0.0, 1.0, 0.0])
    b = z * np.array([3.0, 1.0, 0.5])
    expected = 1.0 + (1.0 - 3.0) ** 2 + (2.0 - 1.0) ** 2 + 0.0
    assert frechet_distance(a, b) == pytest.approx(expected, rel=1e-9)


def test_fid_agrees_with_scipy_sqrtm_formula():
    a, b = _gauss(300, 6, seed=2), _gauss(200, 6, shift=0.3, scale=1.4, seed=3)
    sa, sb = np.cov(a, rowvar=False), np.cov(b, rowvar=False)
    covmean = linalg.sqrtm(sa @ sb).real
    ref = np.sum((a.mean(0) - b.mean(0)) ** 2) + np.trace(sa + sb - 2 * covmean)
    assert frechet_distance(a, b) == pytest.approx(ref, rel=1e-7)


def test_fid_and_kid_are_symmetric():
    a, b = _gauss(300, seed=4), _gauss(250, shift=0.5, seed=5)
    assert frechet_distance(a, b) == pytest.approx(frechet_distance(b, a), rel=1e-9)
    assert kernel_distance(a, b)[0] == pytest.approx(kernel_distance(b, a)[0], rel=1e-9)


def test_shifted_set_scores_worse_and_monotonically():
    real = _gauss(600, seed=6)
    same = _gauss(600, seed=7)
    fids = [frechet_distance(real, _gauss(600, shift=s, seed=8)) for s in (0.0, 0.5, 1.0)]
    kids = [kernel_distance(real, _gauss(600, shift=s, seed=8))[0] for s in (0.0, 0.5, 1.0)]
    assert fids == sorted(fids) and fids[2] > 10 * fids[0]
    assert kids == sorted(kids) and kids[2] > 10 * abs(kids[0])
    p_same, r_same = precision_recall(real, same)
    p_far, r_far = precision_recall(real, _gauss(600, shift=3.0, seed=9))
    assert p_far < 0.5 * p_same and r_far < 0.5 * r_same


def test_kid_matches_a_direct_double_loop():
    a, b = _gauss(12, 4, seed=10), _gauss(9, 4, shift=0.2, seed=11)

    def k(x, y):
        return (x @ y / 4 + 1.0) ** 3

    xx = sum(k(a[i], a[j]) for i in range(12) for j in range(12) if i != j) / (12 * 11)
    yy = sum(k(b[i], b[j]) for i in range(9) for j in range(9) if i != j) / (9 * 8)
    xy = sum(k(a[i], b[j]) for i in range(12) for j in range(9)) / (12 * 9)
    assert kernel_distance(a, b)[0] == pytest.approx(xx + yy - 2 * xy, rel=1e-10)


def test_kid_is_near_zero_for_same_distribution_with_a_sane_std_err():
    a, b = _gauss(1000, seed=12), _gauss(1000, seed=13)
    kid, se = kernel_distance(a, b, n_blocks=10)
    assert se > 0 and np.isfinite(se)
    assert abs(kid) < 4 * se  # unbiased: zero within a few standard errors
    far, far_se = kernel_distance(a, _gauss(1000, shift=1.0, seed=14))
    assert far > 10 * far_se


def test_precision_recall_known_answers():
    real = _gauss(400, 2, seed=15)
    assert precision_recall(real, real) == (1.0, 1.0)
    # fakes collapsed onto a tiny cluster at the mode: precise but no recall
    collapsed = _gauss(400, 2, scale=0.01, seed=16)
    p, r = precision_recall(real, collapsed)
    assert p > 0.95 and r < 0.1


def test_diversity_scales_with_spread_and_ignores_order():
    a = _gauss(500, seed=17)
    assert diversity(a * 3) == pytest.approx(3 * diversity(a), rel=1e-9)
    # E|x - y| for x, y ~ N(0, I_8) is sqrt(2) * E[chi_8] = sqrt(2) * sqrt(2) * Gamma(4.5) / Gamma(4)
    expected = 2.0 * special.gamma(4.5) / special.gamma(4.0)
    assert diversity(a, n_pairs=5000) == pytest.approx(expected, rel=0.05)


def test_all_metrics_invariant_to_sample_order():
    a, b = _gauss(300, seed=18), _gauss(280, shift=0.3, seed=19)
    rng = np.random.default_rng(20)
    m1 = distribution_metrics(a, b)
    m2 = distribution_metrics(a[rng.permutation(300)], b[rng.permutation(280)])
    for key in m1:
        assert m2[key] == pytest.approx(m1[key], rel=1e-9, abs=1e-12), key


@pytest.mark.parametrize(
    "a,b,match",
    [
        (np.zeros((5, 3)), np.zeros((5, 4)), "dimensions differ"),
        (np.zeros((5,)), np.zeros((5, 4)), "2-D"),
        (np.zeros((1, 3)), np.zeros((5, 3)), "at least"),
        (np.full((5, 3), np.nan), np.zeros((5, 3)), "NaN"),
    ],
)
def test_bad_input_raises_one_clear_error(a, b, match):
    with pytest.raises(ValueError, match=match):
        frechet_distance(a, b)
