"""The per-texel normal fit's model (Lensch et al. 2003, Sec. 9) against the Lafortune BRDF
evaluated directly, its Jacobian against finite differences, and the solver's ``keep_jac``.

``_mixture`` shares each lobe's log-base between the basis slots that have the material's C_x
and C_z (rho_d and N raised / lowered): these checks use :func:`make_bases`' real slots, so a
slot given another slot's lobe by mistake shows up as a wrong prediction.
"""
import numpy as np
import pytest

from reconstruct.frames import tangent_frames, to_local
from reconstruct.lensch.lafortune_fit import model_of
from reconstruct.lensch.lm import levenberg_marquardt
from reconstruct.lensch.normals import _mixture
from reconstruct.lensch.projection import make_bases


def _problem(seed=0, m=40, M=25, bases="two"):
    """Bases of 4 slots, m texels of M samples about +z, slopes and weights. ``bases``: "two"
    materials (material, rho_d and N up, down, the other material), "one" (its 4th slot repeats
    its 1st, as a lone material's does) or "alone" (one material, its lobes alone in the 4th)."""
    rng = np.random.default_rng(seed)
    mats = np.array([[[0.6, -0.9, 0.8, 18.0, -0.4, 0.5, 3.0]] * 3,
                     [[0.3, -1.1, 1.0, 40.0, -0.2, 0.3, 2.0]] * 3]) * rng.uniform(0.9, 1.1, (2, 3, 7))
    if bases == "two":
        basis, _ = make_bases(mats, np.array([1, 0]))
    else:
        basis, _ = make_bases(mats[:1], np.array([-1]), lobes_alone=bases == "alone")
        basis = np.concatenate([basis, basis])   # both labels: the one material
    basis_t = basis[rng.integers(0, 2, m)]
    U = rng.normal(size=(m, M, 3))
    U[..., 2] = np.abs(U[..., 2]) + 0.3
    U /= np.linalg.norm(U, axis=2, keepdims=True)
    V = np.broadcast_to(np.array([0.05, -0.1, 1.0]) / np.linalg.norm([0.05, -0.1, 1.0]), (m, M, 3)).copy()
    x = np.concatenate([rng.uniform(-0.3, 0.3, (m, 2)), rng.uniform(0.2, 1.0, (m, 4))], axis=1)
    return U, V, basis_t, x


@pytest.mark.parametrize("bases", ["two", "one", "alone"])
def test_the_model_is_the_weighted_lafortune_brdfs_about_the_tilted_normal(bases):
    """Residuals with R = 0, W = 1 are the prediction sum_b w_b f_b(wi', wo') cos(theta_i'),
    wi', wo' the samples in the frame of n = (a, b, 1) / |.|; each f_b evaluated by
    :class:`reconstruct.brdf.Lafortune` from the slot's parameters (to 1e-12, relative); also
    where a slot repeats another's lobes (a lone material; its lobes alone)."""
    U, V, basis_t, x = _problem(bases=bases)
    m, M, _ = U.shape
    r, _ = _mixture(x, U, V, np.zeros((m, M, 3)), np.ones((m, M)), basis_t)
    n = np.concatenate([x[:, :2], np.ones((m, 1))], axis=1)
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    frames = np.repeat(tangent_frames(n), M, axis=0)
    wi, wo = to_local(U.reshape(-1, 3), frames), to_local(V.reshape(-1, 3), frames)
    lit = (wi[:, 2] > 0) & (wo[:, 2] > 0)
    expected = np.zeros((m * M, 3))
    for b in range(basis_t.shape[1]):
        f = np.stack([model_of(basis_t[t, b]).evaluate(wi[t * M:(t + 1) * M], wo[t * M:(t + 1) * M])
                      for t in range(m)]).reshape(-1, 3)
        expected += np.repeat(x[:, 2 + b], M)[:, None] * f * np.maximum(wi[:, 2:3], 0.0)
    expected[~lit] = 0.0
    got = r.reshape(-1, 3)
    assert np.allclose(got, expected, rtol=1e-12, atol=1e-12 * np.abs(expected).max())


@pytest.mark.parametrize("bases", ["two", "alone"])
def test_the_jacobian_matches_central_differences(bases):
    """d residual / d (slopes, weights) against central differences (step 1e-6), to 1e-5 of the
    largest entry: the slopes' columns go through the shared log-bases and repeated lobes."""
    U, V, basis_t, x = _problem(seed=1, bases=bases)
    m, M, _ = U.shape
    R = np.random.default_rng(2).uniform(0, 0.5, (m, M, 3))
    W = np.ones((m, M))
    _, J = _mixture(x, U, V, R, W, basis_t)
    h = 1e-6
    for p in range(x.shape[1]):
        dx = np.zeros_like(x)
        dx[:, p] = h
        num = (_mixture(x + dx, U, V, R, W, basis_t)[0] - _mixture(x - dx, U, V, R, W, basis_t)[0]) / (2 * h)
        assert np.allclose(J[..., p], num, atol=1e-5 * np.abs(J).max()), p


def test_keep_jac_false_changes_nothing_but_the_jacobian():
    """The solver without the Jacobian kept: the same parameters, costs and iterations bit for
    bit, and ``jac`` None."""
    U, V, basis_t, x = _problem(seed=3)
    m, M, _ = U.shape
    truth = x.copy()
    R, _ = _mixture(truth, U, V, np.zeros((m, M, 3)), np.ones((m, M)), basis_t)
    R = R.reshape(m, M, 3) + np.random.default_rng(4).normal(0, 0.01, (m, M, 3))
    x0 = np.concatenate([np.zeros((m, 2)), truth[:, 2:]], axis=1)

    def fun(xx, items):
        return _mixture(xx, U[items], V[items], R[items], np.ones((len(items), M)), basis_t[items])
    kept = levenberg_marquardt(fun, x0, max_iter=15, ftol=1e-5, xtol=1e-3)
    lean = levenberg_marquardt(fun, x0, max_iter=15, ftol=1e-5, xtol=1e-3, keep_jac=False)
    assert lean.jac is None and kept.jac.shape == (m, 3 * M, x.shape[1])
    assert np.array_equal(lean.x, kept.x) and np.array_equal(lean.cost, kept.cost)
    assert np.array_equal(lean.n_iter, kept.n_iter)
    assert np.median(np.abs(kept.x[:, :2] - truth[:, :2])) < 0.05   # and it does fit
