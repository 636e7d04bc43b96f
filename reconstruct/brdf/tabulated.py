"""Tabulated isotropic BRDFs: a 3-D (theta_h, theta_d, phi_d) table and a bivariate one.

Both look their values up through the Rusinkiewicz halfway/difference angles of
``reconstruct.coords`` and interpolate multilinearly between table nodes (vectorised: a few
gathers per sample, no per-sample Python).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.ndimage import distance_transform_edt

from ..coords import HALF_PI, from_halfway_difference, halfway_difference, romeiro_st
from .base import BRDF

_WARPS = ("sqrt", "linear")


def _axis_nodes(x: np.ndarray, n: int, periodic: bool):
    """Lower/upper node indices and the upper weight for continuous node coordinates ``x``."""
    if periodic:
        x = np.mod(x, n)
        i0 = np.floor(x).astype(np.intp)
        w = x - i0
        i0 %= n  # x can round up to exactly n
        return i0, (i0 + 1) % n, w
    if n == 1:
        zero = np.zeros(x.shape, np.intp)
        return zero, zero, np.zeros(x.shape)
    x = np.clip(x, 0.0, n - 1)
    i0 = np.minimum(np.floor(x).astype(np.intp), n - 2)
    return i0, i0 + 1, x - i0


def _corners(coords, shape, periodic):
    """(flat index (N,), weight (N,)) for each of the 2^D corners of each sample's cell."""
    strides = np.cumprod((1,) + tuple(shape[:0:-1]))[::-1]
    corners = [(np.intp(0), 1.0)]
    for x, n, p, stride in zip(coords, shape, periodic, strides):
        i0, i1, wu = _axis_nodes(x, n, p)
        lo, hi, wl = i0 * stride, i1 * stride, 1.0 - wu
        corners = [c for idx, w in corners for c in ((idx + lo, w * wl), (idx + hi, w * wu))]
    return corners


class _Nodes:
    """A table flattened to (M, 3) for gathers, with NaN (invalid) entries zero-filled and a
    validity mask precomputed once (not per evaluation)."""

    def __init__(self, table: np.ndarray):
        flat = table.reshape(-1, 3)
        invalid = np.isnan(flat)
        self.has_invalid = bool(invalid.any())
        self.values = np.where(invalid, 0.0, flat) if self.has_invalid else flat
        self.valid = ~invalid if self.has_invalid else None

    def interpolate(self, coords, shape, periodic) -> np.ndarray:
        """Multilinear interpolation at continuous node coordinates ``coords`` -> (N, 3); invalid
        entries are skipped (weights renormalised over the valid corners; 0 where none is)."""
        n = len(coords[0])
        num = np.zeros((n, 3))
        if not self.has_invalid:
            for idx, w in _corners(coords, shape, periodic):
                g = np.take(self.values, idx, axis=0)  # np.take gathers ~4x faster than [idx]
                g *= w[:, None]
                num += g
            return num
        den = np.zeros((n, 3))
        for idx, w in _corners(coords, shape, periodic):
            wv = np.take(self.valid, idx, axis=0) * w[:, None]
            num += wv * np.take(self.values, idx, axis=0)
            den += wv
        return np.divide(num, den, out=np.zeros_like(num), where=den > 1e-12)

    def support(self, coords, shape, periodic) -> np.ndarray:
        """(N,) bool: the sample has a valid corner of non-zero weight in every channel (where
        ``interpolate`` returns a value rather than the 0 of "no data")."""
        if not self.has_invalid:
            return np.ones(len(coords[0]), bool)
        den = np.zeros((len(coords[0]), 3))
        for idx, w in _corners(coords, shape, periodic):
            den += np.take(self.valid, idx, axis=0) * w[:, None]
        return np.all(den > 1e-12, axis=1)


def _check_table(owner: str, table, ndim: int) -> np.ndarray:
    t = np.asarray(table, dtype=np.float64)
    if t.ndim != ndim + 1 or t.shape[-1] != 3 or min(t.shape[:-1]) < 1:
        raise ValueError(f"{owner}.table must have shape ({', '.join('n' * ndim)}, 3) with "
                         f"n >= 1, got {t.shape}")
    if np.any(np.isinf(t)):
        raise ValueError(f"{owner}.table has infinite entries (use NaN for invalid ones)")
    if np.any(t < 0):
        raise ValueError(f"{owner}.table has negative entries (use NaN for invalid ones)")
    return t


@dataclass(frozen=True, eq=False)
class TabulatedIsotropic(BRDF):
    """Measured isotropic BRDF on a (theta_h, theta_d, phi_d) grid, MERL-style, trilinear.

    Node (i, j, k) of ``table`` (n_h, n_d, n_p, 3), in 1/sr RGB, holds f at
    theta_h = (i / n_h)^2 pi/2 (``theta_h_warp="sqrt"``, MERL's warping that crowds nodes near
    the specular peak; ``"linear"``: (i / n_h) pi/2), theta_d = (j / n_d) pi/2 and
    phi_d = k pi / n_p. phi_d is folded into [0, pi) by reciprocity and is periodic there;
    theta_h and theta_d are clamped to the last node (constant extrapolation). These are the
    positions MERL's nearest-bin lookup (BRDFRead.cpp) assigns to its bins, so a MERL table
    reads unchanged; between nodes this model interpolates trilinearly in the warped
    coordinates instead of taking the lower bin. NaN entries mark invalid (unmeasured) nodes:
    they are skipped and the remaining corner weights renormalised. A measured table has no
    diffuse/specular split: ``specular_part()`` is the whole table (the base-class default).

    Parameters
    ----------
    table : ndarray, (n_h, n_d, n_p, 3)
        f_r in 1/sr, >= 0 or NaN; n_p = 1 for a phi_d-independent table.
    theta_h_warp : {"sqrt", "linear"}
    """

    table: np.ndarray
    theta_h_warp: str = "sqrt"

    def __post_init__(self):
        t = _check_table("TabulatedIsotropic", self.table, 3)
        if self.theta_h_warp not in _WARPS:
            raise ValueError(f"TabulatedIsotropic.theta_h_warp must be one of {_WARPS}, "
                             f"got {self.theta_h_warp!r}")
        object.__setattr__(self, "table", t)
        object.__setattr__(self, "_nodes", _Nodes(t))

    @property
    def shape(self) -> tuple[int, int, int]:
        """(n_h, n_d, n_p)."""
        return self.table.shape[:3]

    def node_angles(self):
        """Node positions (theta_h (n_h,), theta_d (n_d,), phi_d (n_p,)) in radians."""
        n_h, n_d, n_p = self.shape
        u = np.arange(n_h) / n_h
        theta_h = (u ** 2 if self.theta_h_warp == "sqrt" else u) * HALF_PI
        return theta_h, np.arange(n_d) / n_d * HALF_PI, np.arange(n_p) / n_p * np.pi

    @classmethod
    def from_brdf(cls, brdf: BRDF, shape=(90, 90, 180), theta_h_warp: str = "sqrt"):
        """Tabulate an isotropic ``brdf`` at the nodes (phi_h = 0); below-horizon nodes -> NaN."""
        if len(shape) != 3 or min(shape) < 1:
            raise ValueError(f"shape must be three positive node counts, got {shape}")
        probe = cls(np.zeros(tuple(shape) + (3,)), theta_h_warp)
        th, td, pd = np.meshgrid(*probe.node_angles(), indexing="ij")
        wi, wo = from_halfway_difference(th, 0.0, td, pd)
        f = brdf.evaluate(wi, wo)
        f[(wi[:, 2] <= 0) | (wo[:, 2] <= 0)] = np.nan
        return cls(f.reshape(tuple(shape) + (3,)), theta_h_warp)

    def _coords(self, wi, wo):
        theta_h, _, theta_d, phi_d = halfway_difference(wi, wo)
        n_h, n_d, n_p = self.shape
        u = theta_h / HALF_PI
        x = (np.sqrt(u) if self.theta_h_warp == "sqrt" else u) * n_h
        return (x, theta_d / HALF_PI * n_d, np.mod(phi_d, np.pi) / np.pi * n_p)

    def _evaluate(self, wi, wo):
        return self._nodes.interpolate(self._coords(wi, wo), self.shape, (False, False, True))

    def defined(self, wi, wo):
        """Above the horizon and next to a measured (non-NaN) node: where ``evaluate``'s value
        is data. Beside invalid cells it returns 0 for "unknown", which averages must skip."""
        ok = super().defined(wi, wo)
        ok[ok] = self._nodes.support(self._coords(np.asarray(wi, float).reshape(-1, 3)[ok],
                                                  np.asarray(wo, float).reshape(-1, 3)[ok]),
                                     self.shape, (False, False, True))
        return ok

    def take(self, index) -> "TabulatedIsotropic":
        """A table is one material: the same model for every sample."""
        return self


@dataclass(frozen=True, eq=False)
class Bivariate(BRDF):
    """Bivariate BRDF f(theta_h, theta_d) on a uniform grid in Romeiro's (s, t), bilinear.

    ``table`` has shape (n_t, n_s, 3) (1/sr, RGB): node (i, j) holds f at
    t_i = i / (n_t - 1) and s_j = j / (n_s - 1), i.e. theta_h = t_i^2 pi/2 and
    theta_d = s_j pi/2 (s = 2 theta_d/pi, t = sqrt(2 theta_h/pi); Romeiro et al. 2008, Sect. 2).
    The model ignores phi_d: it is an isotropic BRDF projected onto (theta_h, theta_d).

    Parameters
    ----------
    table : ndarray, (n_t, n_s, 3)
        f_r in 1/sr, >= 0 or NaN (invalid node, skipped as in ``TabulatedIsotropic``).
    """

    table: np.ndarray

    def __post_init__(self):
        t = _check_table("Bivariate", self.table, 2)
        object.__setattr__(self, "table", t)
        object.__setattr__(self, "_nodes", _Nodes(t))

    @staticmethod
    def node_angles(n_t: int, n_s: int):
        """Node angles (theta_h (n_t,), theta_d (n_s,)) in radians of an (n_t, n_s) grid."""
        return (np.linspace(0.0, 1.0, n_t) ** 2 * HALF_PI, np.linspace(0.0, 1.0, n_s) * HALF_PI)

    @classmethod
    def from_brdf(cls, brdf: BRDF, n_t: int = 32, n_s: int = 32, n_phi: int = 64):
        """Project an isotropic ``brdf`` onto the grid (Romeiro et al.'s f-bar, Eq. 1).

        Each node holds the mean of ``brdf`` over the phi_d for which both directions are
        above the horizon, |cos phi_d| < cot(theta_h) cot(theta_d): ``n_phi`` midpoint samples
        spread over that interval only, so every node is a mean of ``n_phi`` valid values (a
        fixed phi_d grid leaves few or none near grazing). Samples where the model has no value
        (``brdf.defined``: a measured table's unmeasured cells, which evaluate to 0) are left
        out. The grazing edges theta_h = pi/2 and theta_d = pi/2 admit no valid pair, so the
        last node of each axis takes the mean a quarter of its cell inside the edge (the value
        the bilinear cell next to the edge needs). A node with no value at all takes its
        nearest valid node's. The table has no NaN.

        Raises
        ------
        ValueError
            If a count is < 1 (naming it) or ``brdf`` has no value anywhere on the domain.
        """
        if min(n_t, n_s, n_phi) < 1:
            raise ValueError(f"n_t, n_s, n_phi must be >= 1, got {n_t}, {n_s}, {n_phi}")
        theta_h, theta_d = cls.node_angles(n_t, n_s)
        for a in (theta_h, theta_d):
            if len(a) > 1:
                a[-1] -= 0.25 * (a[-1] - a[-2])
        th, td = np.meshgrid(theta_h, theta_d, indexing="ij")
        with np.errstate(divide="ignore", invalid="ignore"):
            c = np.nan_to_num(1.0 / (np.tan(th) * np.tan(td)), nan=np.inf, posinf=np.inf)
        phi0 = np.arccos(np.minimum(c, 1.0))  # valid phi_d: (phi0, pi - phi0)
        u = (np.arange(n_phi) + 0.5) / n_phi
        pd = phi0[..., None] + u * (np.pi - 2 * phi0[..., None])
        wi, wo = from_halfway_difference(th[..., None], 0.0, td[..., None], pd)
        f = brdf.evaluate(wi, wo).reshape(n_t, n_s, n_phi, 3)
        ok = brdf.defined(wi, wo).reshape(n_t, n_s, n_phi, 1)
        count = ok.sum(axis=2)
        table = np.divide(np.where(ok, f, 0.0).sum(axis=2), count,
                          out=np.full((n_t, n_s, 3), np.nan), where=count > 0)
        empty = count[..., 0] == 0
        if empty.all():
            raise ValueError("brdf has no value anywhere on the bivariate domain")
        if empty.any():
            _, (it, js) = distance_transform_edt(empty, return_indices=True)
            table = table[it, js]
        return cls(table)

    def _coords(self, wi, wo):
        theta_h, _, theta_d, _ = halfway_difference(wi, wo)
        s, t = romeiro_st(np.minimum(theta_h, HALF_PI), theta_d)
        n_t, n_s = self.table.shape[:2]
        return t * (n_t - 1), s * (n_s - 1)

    def interpolation_weights(self, wi, wo):
        """Bilinear weights that express f(wi, wo) linearly in the table's nodes.

        For local direction pairs (N, 3) returns ``index`` (N, 4), flat node indices into
        ``table.reshape(-1, 3)``, and ``weight`` (N, 4), summing to 1 per row, so that
        f = sum_c weight[:, c] * table_flat[index[:, c]] — the row of a linear system in the
        unknown table (Romeiro et al.'s rendering constraints, Eqs. 2-5).
        """
        pairs = list(_corners(self._coords(wi, wo), self.table.shape[:2], (False, False)))
        return (np.stack([np.broadcast_to(i, len(wi)) for i, _ in pairs], axis=1),
                np.stack([np.broadcast_to(w, len(wi)) for _, w in pairs], axis=1))

    def _evaluate(self, wi, wo):
        return self._nodes.interpolate(self._coords(wi, wo), self.table.shape[:2],
                                       (False, False))

    def take(self, index) -> "Bivariate":
        """A table is one material: the same model for every sample."""
        return self


@dataclass(frozen=True, eq=False)
class TabulatedCosine(BRDF):
    """f_r cos theta_i on a (theta_h, theta_d, phi_d) grid over the whole phi_d circle, trilinear:
    what a point light's image records per unit irradiance.

    Unlike :class:`TabulatedIsotropic` it assumes no reciprocity (phi_d is not folded, so
    f(wi, wo) and f(wo, wi) are different nodes) and it holds the product a renderer needs: the
    radiance it renders, f_r cos theta_i, is the interpolated value itself, never a node's f_r
    divided by a cosine near the horizon and multiplied by another. It is the perfect table of
    data stored as f_r cos theta (RGL ``.bsdf`` files, ``rgl.py``). Node (i, j, k) of
    ``table`` (n_h, n_d, n_p, 3), 1/sr RGB, holds f_r cos theta_i at theta_h = (i / n_h)^2 pi/2,
    theta_d = (j / n_d) pi/2, phi_d = 2 pi k / n_p; NaN marks a node with a direction below the
    horizon (skipped as in :class:`TabulatedIsotropic`).
    """

    table: np.ndarray

    def __post_init__(self):
        t = _check_table("TabulatedCosine", self.table, 3)
        object.__setattr__(self, "table", t)
        object.__setattr__(self, "_nodes", _Nodes(t))

    @classmethod
    def from_brdf(cls, brdf: BRDF, shape=(90, 90, 360)) -> "TabulatedCosine":
        """Tabulate ``brdf`` (isotropic) times cos theta_i at the nodes (phi_h = 0)."""
        if len(shape) != 3 or min(shape) < 1:
            raise ValueError(f"shape must be three positive node counts, got {shape}")
        n_h, n_d, n_p = shape
        th, td, pd = np.meshgrid((np.arange(n_h) / n_h) ** 2 * HALF_PI,
                                 np.arange(n_d) / n_d * HALF_PI,
                                 np.arange(n_p) / n_p * 2.0 * np.pi, indexing="ij")
        wi, wo = from_halfway_difference(th, 0.0, td, pd)
        g = brdf.evaluate(wi, wo) * wi[:, 2:3]
        g[(wi[:, 2] <= 0) | (wo[:, 2] <= 0)] = np.nan
        return cls(g.reshape(tuple(shape) + (3,)))

    def _evaluate(self, wi, wo):
        theta_h, _, theta_d, phi_d = halfway_difference(wi, wo)
        n_h, n_d, n_p = self.table.shape[:3]
        coords = (np.sqrt(theta_h / HALF_PI) * n_h, theta_d / HALF_PI * n_d,
                  np.mod(phi_d, 2.0 * np.pi) / (2.0 * np.pi) * n_p)
        return self._nodes.interpolate(coords, (n_h, n_d, n_p), (False, False, True)) \
            / wi[:, 2:3]

    def take(self, index) -> "TabulatedCosine":
        """A table is one material: the same model for every sample."""
        return self
