"""Projection of lumitexels into per-cluster BRDF bases, and principal function analysis
(Lensch et al. 2003, Sec. 8, Eqs. 11-13).

A texel's BRDF is f = sum_b t_b f_b with non-negative weights t_b shared by the three colour
channels (Eq. 11); the basis f_1..f_B belongs to the texel's cluster (Sec. 8.1). Bases are held as
an array ``basis`` (K, B, 3, P) of per-channel Lafortune parameters with ``basis_size`` (K,) slots
used per cluster (unused slots are ignored).

:func:`project_chunk` and :func:`cluster_residuals` are pure functions of a chunk of texels
(samples with chunk-local texel indices 0..n-1): a chunked map, local or distributed, runs them
unchanged.
"""
from __future__ import annotations

import numpy as np

from .clustering import sample_errors, texel_mean
from .lafortune_fit import N_MAX, N_MIN, lobe_albedo, model_and_jacobian
from .lm import levenberg_marquardt, nnls_batched

#: Relative change of rho_d and N in the two variants of a cluster's BRDF (Sec. 8.1).
VARIANT_STEP = 0.2


def make_bases(materials: np.ndarray, similar: np.ndarray, *, lobes_alone: bool = False
               ) -> tuple[np.ndarray, np.ndarray]:
    """Per-cluster bases (Sec. 8.1): the cluster's BRDF, two variants with rho_d and N raised and
    lowered by :data:`VARIANT_STEP`, and the most similar other cluster's BRDF; with
    ``lobes_alone`` also (last slot) the cluster's lobes without its diffuse term, so that a
    texel's highlight strength is free of its diffuse albedo (its own weighting of the
    material's lobes, as Sec. 8 weights basis BRDFs).

    Parameters
    ----------
    materials : ndarray (K, 3, P)
        Per-channel Lafortune parameters of the clusters.
    similar : ndarray (K,) int
        For each cluster, the other cluster that fits its texels best (-1: none).

    Returns
    -------
    basis : ndarray (K, 4, 3, P); with ``lobes_alone`` (K, 5, 3, P), (K, 4, 3, P) where no
        cluster has a most similar other
    basis_size : ndarray (K,) int
    """
    K, _, P = materials.shape
    B = 5 if lobes_alone else 4
    basis = np.zeros((K, B, 3, P))
    size = np.full(K, 4)
    for sign, slot in ((1.0, 1), (-1.0, 2)):
        v = materials.copy()
        v[:, :, 0] *= 1 + sign * VARIANT_STEP
        v[:, :, 3::3] = np.clip(v[:, :, 3::3] * (1 + sign * VARIANT_STEP), N_MIN, N_MAX)
        basis[:, slot] = v
    basis[:, 0] = materials
    has = similar >= 0
    basis[has, 3] = materials[similar[has]]
    basis[~has, 3] = materials[~has]
    size[~has] = 3
    if lobes_alone:
        basis[np.arange(K), size] = materials
        basis[np.arange(K), size, :, 0] = 0.0
        size += 1
        basis = basis[:, :size.max()]   # no slot that no cluster uses
    return basis, size


def basis_values(t, z, cos_i, texel, labels, basis, basis_size) -> np.ndarray:
    """f_b(wi, wo) cos(theta_i) of every sample's basis BRDFs, (S, B, 3); unused slots are 0."""
    S = len(t)
    K, B = basis.shape[:2]
    A = np.zeros((S, B, 3))
    cluster = labels[texel]
    for k in range(K):
        sel = np.flatnonzero(cluster == k)
        if len(sel) == 0:
            continue
        for b in range(basis_size[k]):
            A[sel, b] = model_and_jacobian(basis[k, b], t[sel], z[sel], cos_i[sel], want_jac=False)[0].T
    return A


def project_chunk(texel, t, z, cos_i, reflectance, weight, labels, basis, basis_size, *,
                  prior: float = 0.0, select: bool = False, max_albedo: float | None = None, extra=None):
    """Non-negative projection of a chunk of texels into their clusters' bases (Eqs. 11-12).

    Parameters
    ----------
    texel : ndarray (S,) int
        Chunk-local texel of each sample, 0..n-1.
    t, z, cos_i : ndarray (S,)
        Lobe geometry and cos(theta_i) of the samples (local frames).
    reflectance : ndarray (S, 3)
        f_r cos(theta_i), 1/sr.
    weight : ndarray (S,)
        Sample weights.
    labels : ndarray (n,) int
        Cluster of each texel.
    basis, basis_size
        From :func:`make_bases`.
    prior : float
        Weight of a ridge pulling each texel's weights towards (1, 0, ..., 0) (its cluster's
        BRDF), relative to the mean diagonal of its normal equations: keeps texels whose samples
        do not constrain the variants (no highlight seen) from extrapolating. 0: the paper's
        plain non-negative least squares.
    select : bool
        Keep a texel's projection only where it predicts its own samples better than the cluster's
        BRDF alone when each sample is left out in turn (leave-one-out residuals of the weights'
        least squares on their support, see :func:`loo_sse`); elsewhere the weights become
        (1, 0, ..., 0). A texel whose highlight only one sample shows can otherwise fit it exactly
        with a sharper or brighter basis BRDF, and predicts other light positions badly.
    max_albedo : float, optional
        Where the texel's weighted lobes may reflect more than this (sum over basis BRDFs and
        lobes of weight x :func:`~reconstruct.lensch.lafortune_fit.lobe_albedo`, any channel; an
        upper bound of the mixture's albedo) and more than its cluster's BRDF alone, the weights
        become (1, 0, ..., 0): a large weight on a basis BRDF that is ~0 at the texel's samples
        (21.8 seen) fits them and predicts absurd values at other lights.
    extra : ndarray (S, E, 3), optional
        E more columns, f cos of every sample under a texel's own extra BRDFs (0 for texels
        without them: its inter-reflection lobes, ``SvbrdfOptions.interreflection_lobe``), solved
        with the basis weights under the same non-negativity; their weights are returned apart
        (not slots of the basis, so ``max_albedo`` does not count them).

    Returns
    -------
    weights : ndarray (n, B)
        Non-negative weights, the same for the three channels.
    sse : ndarray (n,)
        Weighted residual sum of squares over the texel's samples and channels.
    extra_weight : ndarray (n, E)
        Only with ``extra``: their weights per texel.
    """
    n = len(labels)
    B_all = basis.shape[1]
    # slots none of these texels uses are left out (every support with one is solved for nothing)
    B = int(basis_size[labels].max()) if n else B_all
    A = basis_values(t, z, cos_i, texel, labels, basis[:, :B], basis_size) * np.sqrt(weight)[:, None, None]
    if extra is not None:   # solved as the last slots
        A = np.concatenate([A, extra * np.sqrt(weight)[:, None, None]], axis=1)
    r = reflectance * np.sqrt(weight)[:, None]
    Bx = A.shape[1]
    G = np.empty((n, Bx, Bx))
    for i in range(Bx):
        for j in range(i, Bx):
            G[:, i, j] = G[:, j, i] = np.bincount(texel, np.einsum("sc,sc->s", A[:, i], A[:, j]),
                                                  minlength=n)
    h = np.stack([np.bincount(texel, np.einsum("sc,sc->s", A[:, i], r), minlength=n)
                  for i in range(Bx)], axis=1)
    rr = np.bincount(texel, np.einsum("sc,sc->s", r, r), minlength=n)
    if prior > 0:
        lam = prior * np.einsum("nbb->n", G) / B_all
        G = G + lam[:, None, None] * np.eye(Bx)
        h = h.copy()
        h[:, 0] += lam
        t_, _ = nnls_batched(G, h, rr + lam)
        sse = rr - 2 * np.einsum("nb,nb->n", t_, h - lam[:, None] * np.eye(Bx)[0]) + \
            np.einsum("nb,nbc,nc->n", t_, G - lam[:, None, None] * np.eye(Bx), t_)
        sse = np.maximum(sse, 0.0)
    else:
        t_, sse = nnls_batched(G, h, rr)
    if select or max_albedo is not None:
        own = np.bincount(texel, np.sum((A[:, 0] - r) ** 2, axis=1), minlength=n)
        worse = loo_sse(A, r, texel, G, t_) > own if select else np.zeros(n, bool)
        if max_albedo is not None:
            alone = texel_albedo(np.broadcast_to(np.eye(B)[0], (n, B)), labels, basis[:, :B])
            worse |= texel_albedo(t_[:, :B], labels, basis[:, :B]) > np.maximum(max_albedo, alone) * (1 + 1e-9)
        t_[worse] = np.eye(Bx)[0]
        sse[worse] = own[worse]
    weights = np.pad(t_[:, :B], ((0, 0), (0, B_all - B)))
    return (weights, sse) if extra is None else (weights, sse, t_[:, B:])


def texel_albedo(weights, labels, basis) -> np.ndarray:
    """Upper bound of each texel's lobe albedo, largest over channels, (n,): the sum over its
    basis BRDFs and lobes of weight x :func:`~reconstruct.lensch.lafortune_fit.lobe_albedo`.
    ``weights`` (n, B), ``labels`` (n,), ``basis`` (K, B, 3, P)."""
    alb = lobe_albedo(basis[..., 1::3], basis[..., 2::3], basis[..., 3::3]).sum(axis=-1)  # (K, B, 3)
    return np.einsum("nb,nbc->nc", weights, alb[labels]).max(axis=1)


def loo_sse(A, r, texel, G, weights) -> np.ndarray:
    """Leave-one-out residual sum of squares of each texel's weights, (n,).

    ``A`` (S, B, 3) weighted basis values, ``r`` (S, 3) weighted reflectance, ``G`` (n, B, B) the
    normal equations, ``weights`` (n, B). The least squares on the weights' support left without
    sample s (its three channels) misses it by (I - M_s)^-1 e_s, M_s = A_s G^-1 A_s^T the 3 x 3
    leverage of the sample; a sample with leverage ~1 (the only one that sees a highlight) gives a
    huge leave-one-out residual.
    """
    B = G.shape[1]
    both = (weights != 0)[:, :, None] & (weights != 0)[:, None, :]  # the support
    scale = np.maximum(np.einsum("nbb->n", G) / B, 1e-300)[:, None, None]
    Gi = np.linalg.inv(np.where(both, G + 1e-10 * scale * np.eye(B), np.eye(B))) * both
    e = np.einsum("sbc,sb->sc", A, weights[texel]) - r
    M = np.einsum("sbc,sbd,sde->sce", A, Gi[texel], A)
    I_M = np.eye(3) - M
    ok = np.linalg.det(I_M) > 1e-9
    loo = np.full(len(r), np.inf)
    loo[ok] = np.sum(np.linalg.solve(I_M[ok], e[ok, :, None])[..., 0] ** 2, axis=1)
    return np.bincount(texel, loo, minlength=len(G))


def cluster_residuals(texel, t, z, cos_i, reflectance, weight, labels, materials):
    """Weighted residual sum of squares of each texel under its cluster's BRDF alone, (n,)."""
    n = len(labels)
    sse = np.zeros(n)
    cluster = labels[texel]
    for k in range(len(materials)):
        sel = np.flatnonzero(cluster == k)
        if len(sel):
            e = sample_errors(materials[k], t[sel], z[sel], cos_i[sel], reflectance[sel])
            sse += np.bincount(texel[sel], e * weight[sel], minlength=n)
    return sse


def cluster_errors(t, z, cos_i, reflectance, weight, texel, n_texels, materials, *,
                   relative: bool = False) -> np.ndarray:
    """Eq. 6 (s = 1) of every texel under every cluster's BRDF, (K, n); ``relative``: under
    multiplicative noise (:func:`~reconstruct.lensch.clustering.sample_errors`)."""
    return np.stack([texel_mean(sample_errors(m, t, z, cos_i, reflectance, relative=relative),
                                texel, n_texels, weight) for m in materials])


def pfa_refine(basis_k: np.ndarray, texel, t, z, cos_i, reflectance, weight, *, rounds: int = 2,
               max_iter: int = 15) -> np.ndarray:
    """Principal function analysis of one cluster's basis (Eq. 13): fit all B basis BRDFs at once
    to the cluster's samples, re-projecting the texels into the current basis each round.

    ``basis_k`` (B, 3, P); samples of the cluster's texels with local indices ``texel`` 0..n-1.
    Returns the refined basis (B, 3, P) (the input if no round lowered the error).
    """
    B, _, P = basis_k.shape
    n = int(texel.max()) + 1
    labels = np.zeros(n, np.int64)
    size = np.array([B])
    sw = np.sqrt(weight)
    lo, hi = np.full(P, -np.inf), np.full(P, np.inf)
    lo[0] = 0.0
    lo[3::3], hi[3::3] = N_MIN, N_MAX
    current = basis_k.copy()
    wts, sse = project_chunk(texel, t, z, cos_i, reflectance, weight, labels, current[None], size)
    best = sse.sum()
    for _ in range(rounds):
        tw = wts[texel]  # (S, B) weights of each sample's texel

        def fun(x, items, tw=tw):
            par = x.reshape(len(items), B, P)
            f = np.zeros((len(items), len(t)))
            J = np.empty((len(items), len(t), B * P))
            for b in range(B):
                fb, Jb = model_and_jacobian(par[:, b], t, z, cos_i)
                f += tw[:, b] * fb
                J[:, :, b * P:(b + 1) * P] = Jb * (tw[:, b] * sw)[None, :, None]
            return f * sw - (reflectance.T * sw)[items], J

        x0 = current.transpose(1, 0, 2).reshape(3, B * P)
        res = levenberg_marquardt(fun, x0, lower=np.tile(lo, B), upper=np.tile(hi, B), max_iter=max_iter)
        trial = res.x.reshape(3, B, P).transpose(1, 0, 2)
        w_new, sse_new = project_chunk(texel, t, z, cos_i, reflectance, weight, labels, trial[None], size)
        if sse_new.sum() >= best * (1 - 1e-6):
            break
        current, wts, best = trial, w_new, sse_new.sum()
    return current
