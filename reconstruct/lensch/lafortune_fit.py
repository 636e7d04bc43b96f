"""Fitting the Lafortune model to reflectance samples (Lensch et al. 2003, Sec. 6).

Each colour channel has its own parameters (the paper's choice: one lobe is 4 parameters per
channel, 12 in all), so the three channels are three independent least-squares problems, solved
together by the batched Levenberg-Marquardt of :mod:`reconstruct.lensch.lm` with the analytic
Jacobian below. The model compared with a sample is f_r(wi, wo) * cos(theta_i) (the cosine is in
the measured ``reflectance``, Eq. 6).

Parameter layout per channel: ``[rho_d, cx_1, cz_1, n_1, ..., cx_L, cz_L, n_L]`` (P = 1 + 3L).
Our ``rho_d`` is pi x the paper's rho_d (an albedo: the diffuse term is rho_d / pi).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..brdf import Lafortune
from .lm import covariance, levenberg_marquardt, nnls_batched


class LafortuneFitError(ValueError):
    """Inputs a Lafortune fit cannot use (shapes, non-finite values, too few samples)."""


#: Exponent bounds of a fitted lobe, and its start candidates (Sec. 6.2's "average BRDF").
N_MIN, N_MAX = 0.5, 5000.0
_START_EXPONENTS = np.array([1.0, 3.0, 8.0, 20.0, 50.0, 120.0, 300.0, 800.0])
#: b^n is evaluated as exp(min(n ln b, _LOG_CAP)) so that wild trial steps stay finite.
_LOG_CAP = 60.0
#: Largest directional albedo a fitted lobe may have, in units of :func:`albedo_unit` (1 for
#: reflectance in 1/sr): energy conservation allows 1; the factor 2 is slack for the calibration's
#: scale and :func:`lobe_albedo`'s approximation. Samples that never reach a lobe's peak (an
#: unseen grazing or mirror angle) otherwise let a fit trade a large C against a large N: a lobe
#: with -C_x = 2.5 C_z, harmless at every training light, predicted f_r cos = 10^3 near grazing.
MAX_LOBE_ALBEDO = 2.0
#: Cosines of incidence at which :func:`lobe_albedo` looks for the largest albedo.
_COS_GRID = np.linspace(1.0 / 64, 1.0, 64)
#: A lobe whose axis lies on the horizon keeps about sqrt(pi/2) / (2 pi sqrt(N)) of its
#: 2 pi / (N + 2) cap integral above it (large N); the approximation's floor on the axis cosine.
_GRAZING = float(np.sqrt(np.pi / 2) / (2 * np.pi))


def lobe_geometry(wi: np.ndarray, wo: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The two dot products the isotropic Lafortune lobe sees: (u_x v_x + u_y v_y, u_z v_z), (S,) each."""
    t = wi[:, 0] * wo[:, 0] + wi[:, 1] * wo[:, 1]
    return t, wi[:, 2] * wo[:, 2]


def model_and_jacobian(params: np.ndarray, t: np.ndarray, z: np.ndarray, cos_i: np.ndarray,
                       *, want_jac: bool = True):
    """Lafortune reflectance f_r * cos(theta_i) and its derivative in the parameters.

    Parameters
    ----------
    params : ndarray (B, P)
        Per item (e.g. colour channel) ``[rho_d, cx_1, cz_1, n_1, ...]``, P = 1 + 3L.
    t, z : ndarray (S,) or (B, S)
        :func:`lobe_geometry` of the samples.
    cos_i : ndarray (S,) or (B, S)
        cos(theta_i) = wi_z of the samples.

    Returns
    -------
    value : ndarray (B, S)
        f_r(wi, wo) * cos(theta_i), 1/sr.
    jac : ndarray (B, S, P) or None
        d value / d params.
    """
    B, P = params.shape
    L = (P - 1) // 3
    f = np.broadcast_to(params[:, :1] / np.pi, (B, np.shape(t)[-1])).copy()
    # built parameter-major (each column written contiguously), returned as a (B, S, P) view
    Jt = np.empty((B, P, f.shape[1])) if want_jac else None
    if want_jac:
        Jt[:, 0] = 1.0 / np.pi
    for l in range(L):  # few lobes; vectorised over items and samples
        cx, cz, n = (params[:, 1 + 3 * l + k, None] for k in range(3))
        b = cx * t + cz * z
        lit = b > 0
        safe = np.where(lit, b, 1.0)
        log_b = np.log(safe)
        p = np.where(lit, np.exp(np.minimum(n * log_b, _LOG_CAP)), 0.0)
        f += p
        if want_jac:
            dp_db = n * p / safe   # 0 where unlit: p 0, safe 1
            Jt[:, 1 + 3 * l] = dp_db * t
            Jt[:, 2 + 3 * l] = dp_db * z
            Jt[:, 3 + 3 * l] = p * log_b
    f *= cos_i
    if not want_jac:
        return f, None
    Jt *= np.asarray(cos_i)[..., None, :]
    return f, Jt.transpose(0, 2, 1)


def params_of(model: Lafortune, n_lobes: int | None = None) -> np.ndarray:
    """A Lafortune model's parameters as (3, 1 + 3L) per channel (the fit's layout)."""
    L = model.n_lobes if n_lobes is None else n_lobes
    if model.n_lobes != L:
        raise LafortuneFitError(f"init has {model.n_lobes} lobes, n_lobes is {L}")
    out = np.empty((3, 1 + 3 * L))
    rho = np.asarray(model.rho_d, float)
    if rho.ndim > 1 or rho.size not in (1, 3):
        raise LafortuneFitError("init must be a single (not spatially varying) Lafortune model")
    out[:, 0] = np.broadcast_to(rho.reshape(-1), (3,))
    for k, name in enumerate(("cx", "cz", "n")):
        a = np.atleast_1d(np.asarray(getattr(model, name), float))
        a = a[:, None] if a.ndim == 1 else a
        if a.ndim != 2 or a.shape[1] not in (1, 3):
            raise LafortuneFitError("init must be a single (not spatially varying) Lafortune model")
        out[:, 1 + k::3] = np.broadcast_to(a, (L, 3)).T
    return out


def model_of(params: np.ndarray) -> Lafortune:
    """The Lafortune model of per-channel parameters (3, 1 + 3L)."""
    return Lafortune(rho_d=params[:, 0].copy(), cx=params[:, 1::3].T.copy(),
                     cz=params[:, 2::3].T.copy(), n=params[:, 3::3].T.copy())


def param_names(n_lobes: int) -> tuple[str, ...]:
    """Names of the flat parameter vector of :class:`LafortuneFit` (``rho_d.r``, ``cx1.g``, ...)."""
    groups = ["rho_d"] + [f"{k}{l + 1}" for l in range(n_lobes) for k in ("cx", "cz", "n")]
    return tuple(f"{g}.{c}" for g in groups for c in "rgb")


@dataclass(frozen=True)
class LafortuneFit:
    """Result of :func:`fit_lafortune`.

    Attributes
    ----------
    model : Lafortune
        The fitted BRDF (``rho_d`` (3,) = pi x the paper's rho_d; ``cx``, ``cz``, ``n`` (L, 3)).
    params : ndarray (3 * (1 + 3L),)
        Flat parameters, names in ``names``: ``rho_d.r, rho_d.g, rho_d.b, cx1.r, ..., n1.b, cx2.r ...``.
    covariance : ndarray (P, P)
        Their covariance s^2 (J^T J)^-1 (Sec. 6.2), s^2 the residual variance; channels are fitted
        independently, so cross-channel blocks are zero.
    names : tuple of str
    rms : float
        Root mean square of the (weighted; with ``noise="relative"``: relative) residual
        f_r cos(theta_i) - reflectance over samples
        and channels, 1/sr.
    n_samples : int
        Samples used.
    converged : bool
        All three channel fits met their tolerance.
    n_iter : int
        Most iterations a channel needed.
    """

    model: Lafortune
    params: np.ndarray
    covariance: np.ndarray
    names: tuple
    rms: float
    n_samples: int
    converged: bool
    n_iter: int

    @property
    def channel_params(self) -> np.ndarray:
        """Parameters per channel, (3, 1 + 3L): ``[rho_d, cx_1, cz_1, n_1, ...]`` (the fit's layout)."""
        return self.params.reshape(-1, 3).T.copy()

    @property
    def std(self) -> np.ndarray:
        """Standard errors of ``params`` (sqrt of the covariance diagonal)."""
        return np.sqrt(np.diag(self.covariance))

    def report(self) -> str:
        lines = [f"Lafortune fit: {self.model.n_lobes} lobe(s), {self.n_samples} samples, "
                 f"RMS {self.rms:.4g} 1/sr, {'converged' if self.converged else 'NOT converged'} "
                 f"after {self.n_iter} iterations"]
        lines += [f"  {n:8s} {p: .5g} +- {s:.2g}" for n, p, s in zip(self.names, self.params, self.std)]
        return "\n".join(lines)


def check_samples(wi, wo, reflectance, weight=None, *, error=LafortuneFitError):
    """Validated float64 copies of sample arrays (S, 3), (S, 3), (S, 3), (S,); errors name the argument."""
    arrays = {}
    for name, a in (("wi", wi), ("wo", wo), ("reflectance", reflectance)):
        a = np.asarray(a, dtype=np.float64)
        if a.ndim != 2 or a.shape[1] != 3:
            raise error(f"{name} must have shape (S, 3), got {a.shape}")
        if not np.all(np.isfinite(a)):
            raise error(f"{name} holds {int(np.sum(~np.isfinite(a)))} non-finite values")
        arrays[name] = a
    S = len(arrays["wi"])
    for name in ("wo", "reflectance"):
        if len(arrays[name]) != S:
            raise error(f"{name} has {len(arrays[name])} rows, wi has {S}")
    for name in ("wi", "wo"):
        norm = np.linalg.norm(arrays[name], axis=1)
        if np.any(np.abs(norm - 1) > 1e-3):
            raise error(f"{name} must hold unit vectors (local frame); norms range "
                        f"{norm.min():.4g}..{norm.max():.4g}")
        if np.any(arrays[name][:, 2] <= 0):
            raise error(f"{name} has {int(np.sum(arrays[name][:, 2] <= 0))} directions at or below "
                        "the surface (z <= 0); drop those samples first")
    if weight is None:
        w = np.ones(S)
    else:
        w = np.asarray(weight, dtype=np.float64)
        if w.shape != (S,):
            raise error(f"weight must have shape ({S},), got {w.shape}")
        if not np.all(np.isfinite(w)) or np.any(w < 0):
            raise error("weight must be finite and >= 0")
    return arrays["wi"], arrays["wo"], arrays["reflectance"], w


def initial_params(t, z, cos_i, reflectance, weight, n_lobes: int) -> np.ndarray:
    """An average BRDF to start from (Sec. 6.2): diffuse + Phong lobes of a few exponents fitted
    by non-negative least squares; the ``n_lobes`` exponents carrying most energy are kept.
    Returns (3, 1 + 3L)."""
    cos_mirror = z - t  # cos of the angle between wo and the mirror direction of wi
    sw = np.sqrt(weight)[:, None]
    cols = [cos_i / np.pi] + [np.maximum(cos_mirror, 0.0) ** N * cos_i for N in _START_EXPONENTS]
    A = np.stack(cols, axis=1) * sw
    rw = reflectance * sw
    G = A.T @ A
    amps, _ = nnls_batched(np.broadcast_to(G, (3,) + G.shape), rw.T @ A, np.sum(rw * rw, axis=0))
    energy = (amps[:, 1:] * A[:, 1:].mean(axis=0)).sum(axis=0)
    order = np.argsort(-energy, kind="stable")
    chosen = np.sort(order[:n_lobes])
    out = np.empty((3, 1 + 3 * n_lobes))
    out[:, 0] = amps[:, 0]
    floor = 1e-3 * max(float(np.abs(reflectance).max()), 1e-12)
    for l, k in enumerate(chosen):
        N = _START_EXPONENTS[k]
        amp = np.maximum(amps[:, 1 + k], floor)
        c = amp ** (1.0 / N)
        out[:, 1 + 3 * l], out[:, 2 + 3 * l], out[:, 3 + 3 * l] = -c, c, N
    return out


def albedo_unit(reflectance, weight=None) -> float:
    """The data's reflectance unit for :data:`MAX_LOBE_ALBEDO`: 1 (1/sr) or, for data in larger
    relative units (no absolute calibration), pi x the median sample (a diffuse albedo scale)."""
    r = np.asarray(reflectance, float).mean(axis=-1)
    if weight is not None:
        r = r[np.asarray(weight) > 0]
    return max(1.0, np.pi * float(np.median(r))) if r.size else 1.0


def lobe_albedo(cx, cz, n, *, grad: bool = False):
    """Largest directional albedo over incidence of Lafortune lobes max(0, C.(u, v))^N.

    For incidence u the lobe is |w|^N cos^N of the angle to w = (C_x u_x, C_x u_y, C_z u_z), and
    its albedo int f cos(theta_o) dv is |w|^N 2 pi / (N + 2) w_z / |w| when the lobe lies above
    the horizon (exact then; near the horizon the axis cosine is floored at
    ``_GRAZING / sqrt(N + 2)``). The maximum is taken over a grid of cos(theta_i); a physical
    lobe has albedo <= 1 (the paper's normalised Phong lobe: its rho_s).

    Parameters
    ----------
    cx, cz, n : array_like, same shape (...)
        Lobe parameters.
    grad : bool
        Also return d ln(albedo) / d (cx, cz, n) at the maximising incidence, each (...).

    Returns
    -------
    albedo : ndarray (...)
        Dimensionless, in the units of the parameters' reflectance (1/sr x sr).
    """
    cx, cz, n = (np.asarray(a, float)[..., None] for a in (cx, cz, n))
    c2 = _COS_GRID ** 2
    Q = np.maximum(cx ** 2 * (1 - c2) + cz ** 2 * c2, 1e-300)
    axis_z = cz * _COS_GRID / np.sqrt(Q)
    floor = _GRAZING / np.sqrt(n + 2)
    on_axis = axis_z > floor
    log_a = 0.5 * n * np.log(Q) + np.log(2 * np.pi / (n + 2)) + np.log(np.where(on_axis, axis_z, floor))
    k = np.argmax(log_a, axis=-1)[..., None]
    with np.errstate(over="ignore"):  # inf for a runaway lobe: beyond any bound, as it should be
        albedo = np.exp(np.take_along_axis(log_a, k, -1)[..., 0])
    if not grad:
        return albedo
    Q, ax, cg = np.take_along_axis(Q, k, -1), np.take_along_axis(on_axis, k, -1), _COS_GRID[k]
    cx, cz, n = (np.broadcast_to(a, Q.shape) for a in (cx, cz, n))
    m = np.where(ax, n - 1, n)  # ln(axis_z) = ln(cz c) - ln(Q) / 2 on the axis branch
    d_cx = m * cx * (1 - cg ** 2) / Q
    d_cz = m * cz * cg ** 2 / Q + np.where(ax, 1 / np.where(ax, cz, 1.0), 0.0)
    d_n = 0.5 * np.log(Q) - 1 / (n + 2) - np.where(ax, 0.0, 0.5 / (n + 2))
    return albedo, (d_cx[..., 0], d_cz[..., 0], d_n[..., 0])


def albedo_penalty(params: np.ndarray, scale: np.ndarray, limit: float = MAX_LOBE_ALBEDO):
    """Hinge residual per lobe on ``ln lobe_albedo - ln limit`` (zero for any physical lobe when
    ``limit`` >= 1 in the data's units), times ``scale`` (B,); returns (B, L) and its Jacobian
    (B, L, P)."""
    B, P = params.shape
    L = (P - 1) // 3
    cx, cz, n = params[:, 1::3], params[:, 2::3], params[:, 3::3]  # (B, L)
    albedo, (d_cx, d_cz, d_n) = lobe_albedo(cx, cz, n, grad=True)
    on = albedo > limit
    s = np.where(on, scale[:, None], 0.0)
    pen = s * (np.log(np.maximum(albedo, 1e-300)) - np.log(limit))
    dpen = np.zeros((B, L, P))
    lobes = np.arange(L)
    dpen[:, lobes, 1 + 3 * lobes] = s * d_cx
    dpen[:, lobes, 2 + 3 * lobes] = s * d_cz
    dpen[:, lobes, 3 + 3 * lobes] = s * d_n
    return pen, dpen


def lafortune_lm(params0: np.ndarray, t, z, cos_i, reflectance, weight, *, max_iter: int = 200,
                 max_albedo: float = MAX_LOBE_ALBEDO, stall: tuple[int, float] | None = None):
    """Levenberg-Marquardt of the per-channel parameters (3, P) on given samples.

    Returns the :class:`~reconstruct.lensch.lm.LMResult` (items = channels). Bounds keep
    rho_d >= 0 and N in [N_MIN, N_MAX]; a penalty keeps each lobe's albedo <= ``max_albedo``;
    ``stall`` as :func:`~reconstruct.lensch.lm.levenberg_marquardt`'s.
    """
    P = params0.shape[1]
    sw = np.sqrt(weight)
    target = (reflectance.T * sw)  # (3, S)

    scale = np.sqrt(np.sum(target * target, axis=1)) + 1e-12  # penalty ~ the whole signal

    def fun(x, items):
        f, J = model_and_jacobian(x, t, z, cos_i)
        pen, dpen = albedo_penalty(x, scale[items], max_albedo)
        S = len(sw)
        jac = np.empty((len(items), S + dpen.shape[1], P))   # filled in place: no concatenated copy
        np.multiply(J, sw[:, None], out=jac[:, :S])
        jac[:, S:] = dpen
        return np.concatenate([f * sw - target[items], pen], axis=1), jac

    lower = np.full(P, -np.inf)
    upper = np.full(P, np.inf)
    lower[0] = 0.0
    lower[3::3], upper[3::3] = N_MIN, N_MAX
    # a relative cost change of 1e-8 per step is far below any noise; multi-lobe fits crawl
    # along flat valleys (lobes trading energy) long after that
    return levenberg_marquardt(fun, params0, lower=lower, upper=upper, max_iter=max_iter, ftol=1e-8, stall=stall)


def fit_lafortune(wi, wo, reflectance, *, weight=None, n_lobes: int = 1,
                  init: Lafortune | LafortuneFit | None = None, noise: str = "absolute",
                  max_iter: int = 200, max_albedo: float | None = None) -> LafortuneFit:
    """Fit an isotropic Lafortune BRDF to reflectance samples by Levenberg-Marquardt (Sec. 6).

    Parameters
    ----------
    wi, wo : array_like (S, 3)
        Unit directions to the light and to the camera in the local frame (normal = +z, pointing
        away from the surface), z > 0.
    reflectance : array_like (S, 3)
        Measured f_r * cos(theta_i) per sample, RGB, 1/sr (as in ``Lumitexels``).
    weight : array_like (S,), optional
        Non-negative sample weights (least squares in ``weight * residual^2``); default 1.
    n_lobes : int
        Number of lobes L >= 1.
    init : Lafortune or LafortuneFit, optional
        Start point (L lobes); default: an average BRDF from the data (diffuse + the L strongest
        of a few Phong lobes, by non-negative least squares).
    noise : {"absolute", "relative"}
        "absolute": least squares in the reflectance itself (errors of equal size everywhere);
        "relative": multiplicative noise (e.g. the paper's synthetic +-5 %), each sample weighted
        by 1 / model^2, iteratively reweighted from the previous round's model.
    max_iter : int
        Cap on LM iterations per channel.
    max_albedo : float, optional
        Largest directional albedo of a lobe (:func:`lobe_albedo`, per channel); default
        :data:`MAX_LOBE_ALBEDO` x :func:`albedo_unit` of the samples. Lobes beyond it are
        penalised: samples that miss a lobe's peak cannot pin it, and it would predict absurd
        values at untried angles.

    Returns
    -------
    LafortuneFit
        Model (``rho_d`` = pi x the paper's rho_d), flat parameters with their covariance, RMS,
        sample count, convergence.

    Raises
    ------
    LafortuneFitError
        Wrong shapes, non-finite values, directions below the surface, or fewer samples with
        non-zero weight than the 1 + 3L parameters of a channel.
    """
    if isinstance(n_lobes, bool) or not isinstance(n_lobes, (int, np.integer)) or n_lobes < 1:
        raise LafortuneFitError(f"n_lobes must be an integer >= 1, got {n_lobes!r}")
    wi, wo, r, w = check_samples(wi, wo, reflectance, weight)
    P = 1 + 3 * n_lobes
    n_used = int(np.count_nonzero(w))
    if n_used < P:
        raise LafortuneFitError(f"reflectance has {n_used} samples with non-zero weight, fewer than "
                                f"the {P} parameters per channel of a {n_lobes}-lobe Lafortune model")
    t, z = lobe_geometry(wi, wo)
    p0 = None if init is None else params_of(init.model if isinstance(init, LafortuneFit) else init,
                                              n_lobes)
    return fit_geometry(t, z, wi[:, 2], r, w, n_lobes=n_lobes, init=p0, noise=noise, max_iter=max_iter,
                        max_albedo=max_albedo)


def fit_geometry(t, z, cos_i, reflectance, weight, *, n_lobes: int = 1, init: np.ndarray | None = None,
                 noise: str = "absolute", max_iter: int = 200,
                 max_albedo: float | None = None, stall: tuple[int, float] | None = None) -> LafortuneFit:
    """:func:`fit_lafortune` on validated samples given by their :func:`lobe_geometry` (t, z),
    cos(theta_i) (S,), ``reflectance`` (S, 3) and ``weight`` (S,); ``init`` (3, 1 + 3L) or None;
    ``stall`` (window, rtol): stop where the cost fell by less than rtol over window iterations
    (:func:`~reconstruct.lensch.lm.levenberg_marquardt`; None: ``ftol`` or ``max_iter`` only)."""
    P = 1 + 3 * n_lobes
    if max_albedo is None:
        max_albedo = MAX_LOBE_ALBEDO * albedo_unit(reflectance, weight)
    n_used = int(np.count_nonzero(weight))
    p0 = initial_params(t, z, cos_i, reflectance, weight, n_lobes) if init is None else init
    res = lafortune_lm(p0, t, z, cos_i, reflectance, weight, max_iter=max_iter, max_albedo=max_albedo,
                       stall=stall)
    if noise == "relative":
        # multiplicative noise: weight by 1 / model^2 of the previous round (iteratively
        # reweighted; the model, not the noisy sample, sets the weight, so no bias toward low values)
        for _ in range(2):
            f = model_and_jacobian(res.x, t, z, cos_i, want_jac=False)[0].mean(axis=0)
            floor = 0.01 * max(float(np.median(f)), 1e-12)
            weight_rel = weight / np.maximum(f, floor) ** 2
            res = lafortune_lm(res.x, t, z, cos_i, reflectance, weight_rel, max_iter=max_iter,
                               max_albedo=max_albedo, stall=stall)
        weight = weight_rel
    elif noise != "absolute":
        raise LafortuneFitError(f"noise must be 'absolute' or 'relative', got {noise!r}")
    cov_c = covariance(res.jac, res.cost, n_used)  # (3, P, P)
    # flat layout: parameter-major, channel-minor (rho_d.r, rho_d.g, rho_d.b, cx1.r, ...)
    cov = np.zeros((P, 3, P, 3))
    for c in range(3):
        cov[:, c, :, c] = cov_c[c]
    rms = float(np.sqrt(2 * res.cost.sum() / (3 * max(weight.sum(), 1e-300))))
    return LafortuneFit(model=model_of(res.x), params=res.x.T.ravel().copy(),
                        covariance=cov.reshape(3 * P, 3 * P), names=param_names(n_lobes),
                        rms=rms, n_samples=len(t), converged=bool(res.converged.all()),
                        n_iter=int(res.n_iter.max()))
