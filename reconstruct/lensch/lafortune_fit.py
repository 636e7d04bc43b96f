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
#: A lobe's peak max(|C_x|, |C_z|)^N may exceed the energy-normalised Phong peak (N + 2) / 2 pi
#: by at most this factor. Samples that never reach the peak (b < 1 everywhere) otherwise let a
#: fit trade a large C against a large N, and the model explodes (1e49 seen) at untried angles.
#: 1e3 leaves every physical lobe free (an off-specular -C_x = 1.12 C_z at N = 30: 30x).
PEAK_FACTOR = 1e3


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
    J = np.empty((B, f.shape[1], P)) if want_jac else None
    if want_jac:
        J[:, :, 0] = 1.0 / np.pi
    for l in range(L):  # few lobes; vectorised over items and samples
        cx, cz, n = (params[:, 1 + 3 * l + k, None] for k in range(3))
        b = cx * t + cz * z
        lit = b > 0
        log_b = np.log(np.where(lit, b, 1.0))
        p = np.where(lit, np.exp(np.minimum(n * log_b, _LOG_CAP)), 0.0)
        f += p
        if want_jac:
            dp_db = np.where(lit, n * p / np.where(lit, b, 1.0), 0.0)
            J[:, :, 1 + 3 * l] = dp_db * t
            J[:, :, 2 + 3 * l] = dp_db * z
            J[:, :, 3 + 3 * l] = p * log_b
    f *= cos_i
    if want_jac:
        J *= np.asarray(cos_i)[..., None]
    return f, J


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


def peak_penalty(params: np.ndarray, scale: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Hinge residual per lobe on ``N ln max(|C_x|, |C_z|) - ln(PEAK_FACTOR (N + 2) / 2 pi)``
    (zero for any physical lobe), times ``scale`` (B,); returns (B, L) and its Jacobian (B, L, P)."""
    B, P = params.shape
    L = (P - 1) // 3
    pen = np.zeros((B, L))
    dpen = np.zeros((B, L, P))
    for l in range(L):
        c = params[:, 1 + 3 * l:3 + 3 * l]
        n = params[:, 3 + 3 * l]
        k = np.argmax(np.abs(c), axis=1)
        cm = np.maximum(np.abs(c[np.arange(B), k]), 1e-300)
        excess = n * np.log(cm) - np.log(PEAK_FACTOR * (n + 2) / (2 * np.pi))
        on = excess > 0
        pen[:, l] = np.where(on, scale * excess, 0.0)
        dpen[:, l, 3 + 3 * l] = np.where(on, scale * (np.log(cm) - 1 / (n + 2)), 0.0)
        sign = np.sign(c[np.arange(B), k])
        dpen[np.arange(B), l, 1 + 3 * l + k] = np.where(on, scale * n / cm * sign, 0.0)
    return pen, dpen


def lafortune_lm(params0: np.ndarray, t, z, cos_i, reflectance, weight, *, max_iter: int = 200):
    """Levenberg-Marquardt of the per-channel parameters (3, P) on given samples.

    Returns the :class:`~reconstruct.lensch.lm.LMResult` (items = channels). Bounds keep
    rho_d >= 0 and N in [N_MIN, N_MAX].
    """
    P = params0.shape[1]
    sw = np.sqrt(weight)
    target = (reflectance.T * sw)  # (3, S)

    scale = np.sqrt(np.sum(target * target, axis=1)) + 1e-12  # penalty ~ the whole signal

    def fun(x, items):
        f, J = model_and_jacobian(x, t, z, cos_i)
        pen, dpen = peak_penalty(x, scale[items])
        return (np.concatenate([f * sw - target[items], pen], axis=1),
                np.concatenate([J * sw[:, None], dpen], axis=1))

    lower = np.full(P, -np.inf)
    upper = np.full(P, np.inf)
    lower[0] = 0.0
    lower[3::3], upper[3::3] = N_MIN, N_MAX
    # a relative cost change of 1e-8 per step is far below any noise; multi-lobe fits crawl
    # along flat valleys (lobes trading energy) long after that
    return levenberg_marquardt(fun, params0, lower=lower, upper=upper, max_iter=max_iter, ftol=1e-8)


def fit_lafortune(wi, wo, reflectance, *, weight=None, n_lobes: int = 1,
                  init: Lafortune | LafortuneFit | None = None, noise: str = "absolute",
                  max_iter: int = 200) -> LafortuneFit:
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
    return fit_geometry(t, z, wi[:, 2], r, w, n_lobes=n_lobes, init=p0, noise=noise, max_iter=max_iter)


def fit_geometry(t, z, cos_i, reflectance, weight, *, n_lobes: int = 1, init: np.ndarray | None = None,
                 noise: str = "absolute", max_iter: int = 200) -> LafortuneFit:
    """:func:`fit_lafortune` on validated samples given by their :func:`lobe_geometry` (t, z),
    cos(theta_i) (S,), ``reflectance`` (S, 3) and ``weight`` (S,); ``init`` (3, 1 + 3L) or None."""
    P = 1 + 3 * n_lobes
    n_used = int(np.count_nonzero(weight))
    p0 = initial_params(t, z, cos_i, reflectance, weight, n_lobes) if init is None else init
    res = lafortune_lm(p0, t, z, cos_i, reflectance, weight, max_iter=max_iter)
    if noise == "relative":
        # multiplicative noise: weight by 1 / model^2 of the previous round (iteratively
        # reweighted; the model, not the noisy sample, sets the weight, so no bias toward low values)
        for _ in range(2):
            f = model_and_jacobian(res.x, t, z, cos_i, want_jac=False)[0].mean(axis=0)
            floor = 0.01 * max(float(np.median(f)), 1e-12)
            weight_rel = weight / np.maximum(f, floor) ** 2
            res = lafortune_lm(res.x, t, z, cos_i, reflectance, weight_rel, max_iter=max_iter)
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
