"""Smoothness priors of passive reflectometry, learned from a library of BRDFs (Romeiro et al.
2008, Eq. 6): the variance, at every node of the bivariate (t, s) grid, of the BRDF's
derivatives along s and t across the library.

The paper learned them from the MERL database. Ours come from the analytic models over their
parameter ranges (``prior_library``), reduced with ``Bivariate.from_brdf``; a user with MERL
files adds them with ``reconstruct.merl.read_merl``::

    brdfs = prior_library("glossy") + [read_merl(p) for p in paths]
    prior = learn_prior(brdfs, (32, 32))

The two-prior variant of the paper solves once with a prior that prefers diffuse reflectance
(learned from matte and rough materials) and once with one that prefers gloss (learned from
shiny ones), keeping the solution with the lower residual.
"""
from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import numpy as np

from .brdf import BRDF, Bivariate, CookTorrance, Lafortune, Lambertian, OrenNayar, Ward
from .passive_lighting import check_grid

PRIOR_KINDS = ("diffuse", "glossy")
#: phi_d samples per node when reducing a library member: a derivative variance needs no more
#: (64 changes the learned variances by <= 1.5 %, median 1e-14, and costs 4x the time).
PRIOR_PHI_SAMPLES = 16


@dataclass(frozen=True, eq=False)
class SmoothnessPrior:
    """Per-node variances of the bivariate BRDF's finite differences, (1/sr)^2.

    Attributes
    ----------
    var_s : ndarray of shape (n_t, n_s - 1)
        Variance of f[i, j + 1] - f[i, j] (the s-derivative times the node spacing).
    var_t : ndarray of shape (n_t - 1, n_s)
        Variance of f[i + 1, j] - f[i, j].
    name : str
        What it was learned from.
    n_brdfs : int
        Library size.
    """

    var_s: np.ndarray
    var_t: np.ndarray
    name: str = "custom"
    n_brdfs: int = 0

    @property
    def grid(self) -> tuple[int, int]:
        """(n_t, n_s)."""
        return self.var_s.shape[0], self.var_t.shape[1]

    def difference_operators(self):
        """Weighted difference rows (D_s / sigma_s, D_t / sigma_t) as one dense matrix of shape
        (n_t (n_s - 1) + (n_t - 1) n_s, n_t n_s) acting on the flat table (``i * n_s + j``)."""
        n_t, n_s = self.grid
        idx = np.arange(n_t * n_s).reshape(n_t, n_s)
        pairs = [(idx[:, :-1], idx[:, 1:], self.var_s), (idx[:-1], idx[1:], self.var_t)]
        rows = []
        for lo, hi, var in pairs:
            D = np.zeros((lo.size, n_t * n_s))
            r = np.arange(lo.size)
            w = 1.0 / np.sqrt(var.ravel())
            D[r, lo.ravel()] = -w
            D[r, hi.ravel()] = w
            rows.append(D)
        return np.vstack(rows)


def learn_prior(brdfs, grid=(32, 32), *, name: str = "custom", floor: float = 1e-3):
    """Learn Eq. 6's Sigma_s, Sigma_t from a BRDF library.

    Parameters
    ----------
    brdfs : sequence of BRDF or Bivariate
        Isotropic materials; each is reduced with ``Bivariate.from_brdf`` at ``grid`` (a
        ``Bivariate`` of that grid is used as it is; ``PRIOR_PHI_SAMPLES`` phi_d samples per
        node). Each colour channel counts as a sample.
    grid : (int, int)
        (n_t, n_s) nodes.
    name : str
        Label kept in the result.
    floor : float
        Variances are floored at ``floor`` x their median, so that a node every library member
        agrees on (a zero variance) is strongly, not infinitely, smoothed.

    Returns
    -------
    SmoothnessPrior

    Raises
    ------
    ValueError
        If ``brdfs`` holds fewer than two materials or something that is not a BRDF.
    """
    n_t, n_s = check_grid(grid)
    tables = library_tables(brdfs, grid)
    t = np.moveaxis(tables, -1, 1).reshape(-1, n_t, n_s)  # channels as samples
    var_s = np.var(np.diff(t, axis=2), axis=0)
    var_t = np.var(np.diff(t, axis=1), axis=0)
    lo = floor * np.median(np.concatenate([var_s.ravel(), var_t.ravel()]))
    if not lo > 0:
        raise ValueError("brdfs do not vary: every derivative variance is 0")
    return SmoothnessPrior(np.maximum(var_s, lo), np.maximum(var_t, lo), name, len(tables))


def library_tables(brdfs, grid) -> np.ndarray:
    """Each library member reduced to the (t, s) grid (``Bivariate.from_brdf``; a
    ``Bivariate`` of that grid as it is): (n_brdfs, n_t, n_s, 3), 1/sr."""
    n_t, n_s = check_grid(grid)
    brdfs = list(brdfs)
    if len(brdfs) < 2:
        raise ValueError(f"brdfs must hold at least two materials, got {len(brdfs)}")
    tables = []
    for k, b in enumerate(brdfs):
        if not isinstance(b, BRDF):
            raise ValueError(f"brdfs[{k}] is a {type(b).__name__}, not a reconstruct BRDF")
        if isinstance(b, Bivariate) and b.table.shape[:2] == (n_t, n_s):
            tables.append(b.table)
        else:
            tables.append(Bivariate.from_brdf(b, n_t, n_s, n_phi=PRIOR_PHI_SAMPLES).table)
    return np.stack(tables)


def prior_library(kind: str) -> list[BRDF]:
    """The analytic BRDF library a default prior is learned from.

    ``"diffuse"``: Lambertian and Oren-Nayar (sigma 0.1-0.6) surfaces and rough Cook-Torrance /
    Ward materials (alpha 0.3-0.6). ``"glossy"``: shiny Cook-Torrance (GGX and Beckmann, alpha
    0.04-0.25, dielectric to metallic f0), Ward (alpha 0.05-0.2) and a Lafortune retro-reflector.
    Albedos span dark to bright; all are energy conserving.
    """
    if kind == "diffuse":
        return ([Lambertian(a) for a in (0.1, 0.4, 0.8)]
                + [OrenNayar(a, s) for a in (0.2, 0.7) for s in (0.1, 0.3, 0.6)]
                + [CookTorrance(kd, f0, al, d) for kd in (0.2, 0.6) for f0 in (0.04, 0.2)
                   for al in (0.3, 0.6) for d in ("ggx", "beckmann")]
                + [Ward(0.5, 0.1, al) for al in (0.3, 0.5)])
    if kind == "glossy":
        return ([CookTorrance(kd, f0, al, d) for kd in (0.05, 0.4) for f0 in (0.04, 0.3, 0.9)
                 for al in (0.04, 0.1, 0.25) for d in ("ggx", "beckmann")]
                + [Ward(0.3, rs, al) for rs in (0.05, 0.2) for al in (0.05, 0.1, 0.2)]
                + [Lafortune(0.3, 1.03, 1.03, 12.0)])
    raise ValueError(f"kind must be one of {PRIOR_KINDS}, got {kind!r}")


def default_prior(kind: str, grid=(32, 32)) -> SmoothnessPrior:
    """``learn_prior(prior_library(kind), grid)``, cached per (kind, grid) (seconds to learn)."""
    return _default_prior(kind, *check_grid(grid))


@lru_cache(maxsize=8)
def _default_prior(kind: str, n_t: int, n_s: int) -> SmoothnessPrior:
    return learn_prior(prior_library(kind), (n_t, n_s), name=kind)
