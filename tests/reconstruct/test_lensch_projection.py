"""Projection into basis BRDFs (Lensch et al. 2003, Sec. 8): the batched NNLS and project_chunk."""
import numpy as np
from scipy.optimize import nnls

from reconstruct.lensch.lafortune_fit import lobe_geometry, params_of
from reconstruct.lensch.lm import nnls_batched
from reconstruct.lensch.projection import basis_values, loo_sse, make_bases, project_chunk
from sims.objects import BUMPY_MATERIALS


def test_batched_nnls_equals_scipy_nnls():
    rng = np.random.default_rng(0)
    A = rng.normal(size=(300, 12, 4))
    A[:100, :, 3] = A[:100, :, 2]  # rank-deficient items too
    r = rng.normal(size=(300, 12))
    G = np.einsum("nsb,nsc->nbc", A, A)
    h = np.einsum("nsb,ns->nb", A, r)
    t, sse = nnls_batched(G, h, np.einsum("ns,ns->n", r, r))
    for k in range(300):
        want, res = nnls(A[k], r[k])
        np.testing.assert_allclose(sse[k], res ** 2, rtol=1e-6, atol=1e-9)
        if k >= 100:  # unique solution where A has full rank
            np.testing.assert_allclose(t[k], want, atol=1e-6)
    assert np.all(t >= 0)


def _samples(n, rng):
    texel = np.repeat(np.arange(n), 6)
    v = rng.normal(size=(2, len(texel), 3))
    v[..., 2] = np.abs(v[..., 2]) + 0.2
    v /= np.linalg.norm(v, axis=2, keepdims=True)
    t, z = lobe_geometry(v[0], v[1])
    return texel, t, z, v[0][:, 2]


def test_project_chunk_recovers_known_mixtures_and_the_prior_pulls_to_the_cluster_brdf():
    rng = np.random.default_rng(1)
    n = 400
    texel, t, z, cos_i = _samples(n, rng)
    basis, size = make_bases(np.stack([params_of(m) for m in BUMPY_MATERIALS]), np.array([1, 2, 0]))
    labels = rng.integers(0, 3, n)
    A = basis_values(t, z, cos_i, texel, labels, basis, size)
    truth = rng.random((n, 4)) * (rng.random((n, 4)) > 0.3)  # sparse non-negative mixtures
    r = np.einsum("sbc,sb->sc", A, truth[texel])
    w, sse = project_chunk(texel, t, z, cos_i, r, np.ones(len(r)), labels, basis, size)
    # the variants are nearly collinear on 6 samples (off the highlight only rho_d shows), so the
    # weights need not be unique; the mixture they make must reproduce the samples
    assert np.all(w >= 0)
    # (to the 1e-10 ridge that keeps near-singular normal equations solvable)
    np.testing.assert_allclose(np.einsum("sbc,sb->sc", A, w[texel]), r, rtol=1e-3, atol=1e-5)
    assert sse.sum() < 1e-10 * np.sum(r ** 2)
    # with a ridge towards (1, 0, 0, 0) the reported SSE is still the data's, independently summed
    noisy = A[:, 0] * (1 + 0.05 * rng.normal(size=(len(r), 3)))
    w0, _ = project_chunk(texel, t, z, cos_i, noisy, np.ones(len(r)), labels, basis, size)
    w1, sse1 = project_chunk(texel, t, z, cos_i, noisy, np.ones(len(r)), labels, basis, size, prior=0.05)
    pred = np.einsum("sbc,sb->sc", A, w1[texel])
    np.testing.assert_allclose(sse1, np.bincount(texel, np.sum((pred - noisy) ** 2, axis=1), minlength=n),
                               rtol=1e-8, atol=1e-12)
    e0 = np.eye(4)[0]
    assert np.abs(w1 - e0).mean() < 0.2 * np.abs(w0 - e0).mean()


def test_leave_one_out_errors_equal_refits_without_each_sample():
    """loo_sse against brute force: refit each texel's weights on its support without sample s
    (its three channels) by plain least squares and predict s."""
    rng = np.random.default_rng(3)
    n, per, B = 40, 7, 3
    texel = np.repeat(np.arange(n), per)
    A = rng.random((n * per, B, 3))
    r = rng.random((n * per, 3))
    weights = rng.random((n, B)) * (rng.random((n, B)) > 0.3)
    G = np.zeros((n, B, B))
    np.add.at(G, texel, np.einsum("sbc,sdc->sbd", A, A))
    for k in range(n):  # loo_sse takes ``weights`` as the least squares on their support
        act = np.flatnonzero(weights[k])
        rows = np.flatnonzero(texel == k)
        if len(act):
            X = A[rows][:, act].transpose(0, 2, 1).reshape(-1, len(act))
            weights[k, act] = np.linalg.lstsq(X, r[rows].ravel(), rcond=None)[0]
    got = loo_sse(A, r, texel, G, weights)
    for k in range(n):
        act = np.flatnonzero(weights[k])
        rows = np.flatnonzero(texel == k)
        want = 0.0
        for s in rows:
            others = rows[rows != s]
            X = A[others][:, act].transpose(0, 2, 1).reshape(-1, len(act))
            w = np.linalg.lstsq(X, r[others].ravel(), rcond=None)[0]
            want += np.sum((A[s][act].T @ w - r[s]) ** 2)
        np.testing.assert_allclose(got[k], want, rtol=1e-8, atol=1e-12)
