"""Normal fitting with the projected BRDFs (Lensch et al. 2003, Sec. 9, Eqs. 14-16).

For each texel the normal is tilted away from the mesh normal and the basis weights re-solved so
that f_pi(wi', wo') cos(theta_i') matches the samples, where wi', wo' are the sample directions in
the frame of the tilted normal. The normal is parametrised by its slopes (a, b): n = (a, b, 1) / |.|
in the texel's current local frame (no pole at the mesh normal, unlike the paper's azimuth /
zenith). Because the model is isotropic, only n.wi, n.wo and wi.wo enter, so no tangent is needed.

All texels are solved together by the batched Levenberg-Marquardt (texels grouped by sample
count, samples padded within a group); :func:`fit_normals_chunk` is a pure function of a chunk.
On real photographs the fit can lose a texel's highlight (its brightest samples left out,
light the object reflects onto itself pulling the lobe elsewhere): the optional peak test finds
such texels by their brightest sample, far above the fitted model, and holds their normals near
that sample's half vector (docs/diligent.md, round lensch7).
"""
from __future__ import annotations

import numpy as np

from .lafortune_fit import _LOG_CAP
from .lm import levenberg_marquardt

#: Largest tilt (slope) of a fitted normal from the mesh normal: tan(70 deg).
MAX_SLOPE = float(np.tan(np.radians(70.0)))


def _padded(texel, values, n, counts, members, width):
    """Rows of ``values`` for the texels ``members`` padded to ``width`` samples: (m, width, ...)."""
    starts = np.concatenate([[0], np.cumsum(counts)])[members]
    idx = starts[:, None] + np.arange(width)[None, :]
    valid = np.arange(width)[None, :] < counts[members][:, None]
    idx = np.where(valid, idx, 0)
    return values[idx], valid


def _mixture(x, U, V, R, W, basis_t):
    """Residuals and Jacobian of the tilted-normal model for a group of texels.

    x (m, 2 + B): slopes a, b and weights; U, V, R (m, M, 3); W (m, M) sample weights (0 = pad);
    basis_t (m, B, 3, P) each texel's basis parameters.
    """
    m, M, _ = U.shape
    B = basis_t.shape[1]
    P = basis_t.shape[-1]
    p = np.concatenate([x[:, :2], np.ones((m, 1))], axis=1)
    norm = np.linalg.norm(p, axis=1)
    nrm = p / norm[:, None]
    uz = np.einsum("mk,msk->ms", nrm, U)
    vz = np.einsum("mk,msk->ms", nrm, V)
    uv = np.einsum("msk,msk->ms", U, V)
    zz = uz * vz
    visible = (uz > 0) & (vz > 0)
    F = np.zeros((m, M, 3))
    dF = np.zeros((m, M, 3))
    fb_all = np.empty((m, M, B, 3))
    L = (P - 1) // 3
    # a slot repeating an earlier slot's lobe (one material's 4th slot its 1st, the lobes-alone
    # slot the material's) takes its value and derivative from there
    twins = {(b, l): next((c for c in range(b) if np.array_equal(basis_t[:, c, :, 1 + 3 * l:4 + 3 * l],
                                                                 basis_t[:, b, :, 1 + 3 * l:4 + 3 * l])), None)
             for b in range(B) for l in range(L)}
    repeated = {(c, l) for (_, l), c in twins.items() if c is not None}
    bases = {}   # lobe l's (lit, base, log base) by slot: the variants share the material's C_x, C_z
    lobes = {}   # lobe l's value and d value / d(n.wi n.wo), kept for the slots a twin repeats
    for b in range(B):
        par = basis_t[:, b]  # (m, 3, P)
        fb = np.broadcast_to((par[:, None, :, 0]) / np.pi, (m, M, 3)).copy()
        dfb = np.zeros((m, M, 3))
        for l in range(L):
            cx, cz, N = (par[:, None, :, 1 + 3 * l + k] for k in range(3))
            twin = twins[b, l]
            if twin is None:
                same = next((c for c in range(b) if np.array_equal(basis_t[:, c, :, 1 + 3 * l:3 + 3 * l],
                                                                   par[..., 1 + 3 * l:3 + 3 * l])), None)
                if same is None:
                    base = cx * (uv - zz)[..., None] + cz * zz[..., None]
                    lit = base > 0
                    safe = np.where(lit, base, 1.0)
                    bases[b, l] = lit, safe, np.log(safe)
                else:
                    bases[b, l] = bases[same, l]
                lit, safe, log_base = bases[b, l]
                lobe = np.where(lit, np.exp(np.minimum(N * log_base, _LOG_CAP)), 0.0)
                value = lobe, N * lobe / safe * (cz - cx)   # 0 where unlit: lobe 0, safe 1
                if (b, l) in repeated:
                    lobes[b, l] = value
            else:
                value = lobes[twin, l]
            fb += value[0]
            dfb += value[1]
        fb_all[:, :, b] = fb
        F += x[:, None, None, 2 + b] * fb
        dF += x[:, None, None, 2 + b] * dfb
    sw = np.sqrt(W) * visible
    model = F * uz[..., None]
    res = (model - R) * np.sqrt(W)[..., None]
    res = np.where(visible[..., None], res, -R * np.sqrt(W)[..., None])
    dm_duz = F + (uz * vz)[..., None] * dF
    dm_dvz = (uz * uz)[..., None] * dF
    J = np.empty((m, M, 3, 2 + B))
    for k in range(2):  # d n / d slope_k = (e_k - n n_k) / |p|
        dn = (np.eye(3)[k][None, :] - nrm * nrm[:, k:k + 1]) / norm[:, None]
        duz = np.einsum("mk,msk->ms", dn, U)
        dvz = np.einsum("mk,msk->ms", dn, V)
        J[..., k] = (dm_duz * duz[..., None] + dm_dvz * dvz[..., None]) * sw[..., None]
    J[..., 2:] = (fb_all * uz[..., None, None]).transpose(0, 1, 3, 2) * sw[..., None, None]
    return res.reshape(m, M * 3), J.reshape(m, M * 3, 2 + B)


def _robust_sigma(x, U, V, R, W, basis_t) -> np.ndarray:
    """1.4826 x the median RGB residual norm (1/sr) of each texel's samples with weight > 0 at
    parameters ``x``, (m,); at least 1e-9 (a texel fitted exactly has 0)."""
    r, _ = _mixture(x, U, V, R, W, basis_t)
    e = np.where(W > 0, np.linalg.norm(r.reshape(len(x), U.shape[1], 3), axis=2), np.nan)
    e[~np.any(W > 0, axis=1), 0] = 0.0   # no sample: nothing to fit
    return 1.4826 * np.maximum(np.nanmedian(e, axis=1), 1e-9)


def tukey_loss(e, s):
    """Tukey's biweight loss rho(e) = s^2 / 6 (1 - (1 - (e / s)^2)^3) of residual norms ``e``
    cut off at ``s`` (s^2 / 6 beyond it), broadcast."""
    return s * s / 6.0 * (1.0 - (1.0 - np.minimum((e / s) ** 2, 1.0)) ** 3)


def _tukey(r, J, scale):
    """Residuals (m, 3M) and Jacobian (m, 3M, P) of a least-squares problem turned into Tukey's
    biweight loss on each sample's RGB residual norm e, cut off at ``scale`` (m,): the residuals
    are rescaled so that 0.5 |r'|^2 is the loss rho(e) = s^2 / 6 (1 - (1 - (e / s)^2)^3) (s^2 / 6
    beyond s), and the Jacobian by the square root of the biweight (1 - (e / s)^2)^2 (the
    iteratively reweighted step; the solver accepts a step only where the true loss drops)."""
    m = len(r)
    e = np.linalg.norm(r.reshape(m, -1, 3), axis=2)
    s = scale[:, None]
    u2 = np.minimum((e / s) ** 2, 1.0)
    rho = tukey_loss(e, s)
    k = np.repeat(np.where(e > 0, np.sqrt(2.0 * rho) / np.maximum(e, 1e-300), 1.0), 3, axis=1)
    w = np.repeat(1.0 - u2, 3, axis=1)   # sqrt of the biweight
    return r * k, J * w[..., None]


def _peak_test(x, U, V, R, W, basis_t, ratio: float):
    """Texels whose brightest sample (channel sum, weight > 0) the model at ``x`` underpredicts
    by more than ``ratio``, (m,) bool, and the slopes (m, 2) of that sample's half vector in the
    texels' local frames (a lobe about the texel's normal peaks near it)."""
    m = len(x)
    bright = np.where(W > 0, R.sum(axis=2), -np.inf)
    j = np.argmax(bright, axis=1)
    rows = np.arange(m)
    r, _ = _mixture(x, U, V, R, W, basis_t)
    sw = np.sqrt(W[rows, j])
    model = r.reshape(m, -1, 3)[rows, j] / np.maximum(sw, 1e-300)[:, None] + R[rows, j]
    h = U[rows, j] + V[rows, j]
    h /= np.linalg.norm(h, axis=1, keepdims=True)
    ok = (sw > 0) & (h[:, 2] > 1.0 / np.sqrt(1.0 + MAX_SLOPE ** 2))
    flagged = ok & (R[rows, j].sum(axis=1) > ratio * np.maximum(model.sum(axis=1), 0.0))
    return flagged, h[:, :2] / np.where(ok, h[:, 2], 1.0)[:, None]


def fit_normals_chunk(texel, wi, wo, reflectance, weight, labels, weights, basis, basis_size, *,
                      min_samples: int = 3, max_iter: int = 15, tukey_c: float | None = None,
                      peak_weight=None, peak_ratio: float | None = None, peak_hold: float = 0.05,
                      peak_compare: bool = True, return_axes: bool = False):
    """Fit a normal and basis weights per texel of a chunk (Eq. 16), all texels at once.

    Parameters
    ----------
    texel : ndarray (S,) int
        Chunk-local texel per sample, 0..n-1, **sorted**.
    wi, wo : ndarray (S, 3)
        Local unit directions (mesh-normal frame).
    reflectance : ndarray (S, 3)
        f_r cos(theta_i), 1/sr.
    weight : ndarray (S,)
    labels : ndarray (n,) int
        Cluster per texel.
    weights : ndarray (n, B)
        Starting basis weights (from the projection).
    basis, basis_size
        Per-cluster bases (see :mod:`reconstruct.lensch.projection`).
    min_samples : int
        Texels with fewer samples keep the mesh normal (too few to fix 2 + B unknowns).
    max_iter : int
        Levenberg-Marquardt iterations at most.
    tukey_c : float, optional
        Minimise Tukey's biweight loss of each sample's RGB residual (1/sr) cut off at
        ``tukey_c`` x 1.4826 x the texel's median residual at the start (+z, the given weights)
        instead of the squared residuals (None).
    peak_weight : ndarray (S,), optional
        Weights of all the texels' samples (before any robust selection) for the peak test and
        the refit of the texels it flags (default ``weight``).
    peak_ratio : float, optional
        The peak test (None: none): where a texel's brightest sample (among ``peak_weight`` > 0)
        exceeds ``peak_ratio`` x what the fitted model predicts there, the fit has lost the
        texel's highlight; its normal is fitted again from the half vector of that sample, on
        all its samples, its slopes held within ``peak_hold`` of the half vector's, and kept
        where it fits all those samples at least as well as the free fit's (under Tukey's loss
        with ``tukey_c``: light no lobe about either normal explains counts little).
    peak_compare : bool
        False: keep every held normal (no comparison with the free fit's).
    return_axes : bool
        Also return, for each texel whose held normal was kept, its free fit's normal (the
        inter-reflection's axis, local frame; NaN for the others), (n, 3).

    Returns
    -------
    normals : ndarray (n, 3)
        Fitted unit normals in each texel's local (mesh-normal) frame; +z where not fitted.
    weights : ndarray (n, B)
        Basis weights found with them.
    fitted : ndarray (n,) bool
        Texels whose normal was fitted.
    converged : ndarray (n,) bool
    axes : ndarray (n, 3)
        Only with ``return_axes``.
    """
    n, B = weights.shape
    counts = np.bincount(texel, minlength=n)
    normals = np.tile([0.0, 0.0, 1.0], (n, 1))
    out_w = weights.copy()
    converged = np.zeros(n, bool)
    axes = np.full((n, 3), np.nan)
    fitted = counts >= min_samples
    # groups of similar sample counts, each padded to its largest count
    edges = [min_samples, 5, 9, 17, 33, 65, np.inf]
    for lo, hi in zip(edges[:-1], edges[1:]):
        members = np.flatnonzero((counts >= lo) & (counts < hi))
        if len(members) == 0:
            continue
        width = int(counts[members].max())
        U, valid = _padded(texel, wi, n, counts, members, width)
        V, _ = _padded(texel, wo, n, counts, members, width)
        R, _ = _padded(texel, reflectance, n, counts, members, width)
        Wt, _ = _padded(texel, weight, n, counts, members, width)
        Wt = Wt * valid
        basis_t = basis[labels[members]]
        unused = np.arange(B)[None, :] >= basis_size[labels[members]][:, None]

        x0 = np.concatenate([np.zeros((len(members), 2)), weights[members]], axis=1)
        lower = np.concatenate([np.full((len(members), 2), -MAX_SLOPE), np.zeros((len(members), B))], 1)
        upper = np.concatenate([np.full((len(members), 2), MAX_SLOPE),
                                np.where(unused, 0.0, np.inf)], 1)
        # the loss's scale stays the start's: re-estimating it at the fit and fitting again cost
        # 30 % more CPU and did worse on DiLiGenT than a tighter cut-off (docs/diligent.md)
        scale = None if tukey_c is None else tukey_c * _robust_sigma(x0, U, V, R, Wt, basis_t)

        def fun(x, items, U=U, V=V, R=R, Wt=Wt, basis_t=basis_t, scale=scale):
            if len(items) < len(U):   # the items still iterating (all of them: no copies)
                U, V, R, Wt, basis_t = U[items], V[items], R[items], Wt[items], basis_t[items]
                scale = None if scale is None else scale[items]
            r, J = _mixture(x, U, V, R, Wt, basis_t)
            return (r, J) if scale is None else _tukey(r, J, scale)
        # a slope step of 1e-3 is 0.06 deg: below what a dozen noisy samples resolve
        res = levenberg_marquardt(fun, x0, lower=lower, upper=upper, max_iter=max_iter,
                                  ftol=1e-5, xtol=1e-3, keep_jac=False)
        x = res.x
        if peak_ratio is not None:
            Pw = _padded(texel, weight if peak_weight is None else peak_weight, n, counts, members, width)[0] * valid
            lost, slopes = _peak_test(x, U, V, R, Pw, basis_t, peak_ratio)
            if lost.any():
                x = x.copy()
                held, better = _held_at_peak(x[lost], slopes[lost], peak_hold, U[lost], V[lost], R[lost],
                                             Pw[lost], basis_t[lost], lower[lost], upper[lost], tukey_c, max_iter)
                if not peak_compare:
                    better[:] = True
                keep = np.flatnonzero(lost)[better]
                axes[members[keep]] = _unit(x[keep, :2])
                x[keep] = held[better]
        normals[members] = _unit(x[:, :2])
        out_w[members] = x[:, 2:]
        converged[members] = res.converged
    return (normals, out_w, fitted, converged, axes) if return_axes else (normals, out_w, fitted, converged)


def _unit(slopes) -> np.ndarray:
    """Unit normals (m, 3) of slopes (m, 2): (a, b, 1) / |.|."""
    p = np.concatenate([slopes, np.ones((len(slopes), 1))], axis=1)
    return p / np.linalg.norm(p, axis=1, keepdims=True)


def _held_at_peak(x, slopes, hold, U, V, R, W, basis_t, lower, upper, tukey_c, max_iter):
    """Parameters (m, 2 + B) of texels refitted from the peak's half-vector ``slopes`` (m, 2) with
    the slopes held within ``hold`` of them, on the samples ``W``; and whether they fit those
    samples at least as well as the free fit's parameters ``x`` (m,) bool, under Tukey's loss
    (``tukey_c``, its scale the texel's robust sigma about the peak) or least squares."""
    x0 = np.concatenate([slopes, x[:, 2:]], axis=1)
    lo, hi = lower.copy(), upper.copy()
    lo[:, :2] = np.maximum(slopes - hold, -MAX_SLOPE)
    hi[:, :2] = np.minimum(slopes + hold, MAX_SLOPE)
    x0 = np.clip(x0, lo, hi)
    scale = None if tukey_c is None else tukey_c * _robust_sigma(x0, U, V, R, W, basis_t)

    def fun(xx, items):
        r, J = _mixture(xx, U[items], V[items], R[items], W[items], basis_t[items])
        return (r, J) if scale is None else _tukey(r, J, scale[items])
    res = levenberg_marquardt(fun, x0, lower=lo, upper=hi, max_iter=max_iter, ftol=1e-5, xtol=1e-3,
                              keep_jac=False)
    everyone = np.arange(len(x))
    free = fun(x, everyone)[0]
    return res.x, res.cost <= 0.5 * np.einsum("mk,mk->m", free, free)
