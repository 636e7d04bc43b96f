"""A non-linear prior for the nodes one image does not constrain: the nearest library exemplars.

The modes prior (``passive_modes``) is one Gaussian: it carries the library's *average* linear
relation between the nodes an image sees and those it does not (the sub-degree mirror peak,
the grazing rise beyond the view limit, the retro band). Materials are not Gaussian (metals,
paints, fabrics and plastics each relate their lobe to their peak and grazing rise in their own
way), so here, after the solve, the k library materials whose log tables best match the
recovered one at the constrained nodes stand for the material's kind, and their weighted
average fills the nodes the environment left unconstrained (``fill_unconstrained``). Each
exemplar is first fitted to the recovered table at the constrained nodes, per channel, by a
slope and an offset in log space (a x + b: b a brightness, a how sharp), in least squares
weighted by the nodes' coverage, which also weighs the distance. k is chosen by leave-one-out
on the library itself (``choose_k``): each member's own seen nodes predict its unseen ones
from the others'.

Measured on MERL under Grace (docs/zoo.md): 30 of 100 within the Fig. 6 target against the
modes prior's own extrapolation's 34, and even the best single exemplar picked with the truth's
help reaches only 36; so this is an option, not the default.

Tables are bivariate (t, s) grids flattened as ``i * n_s + j`` (``passive_lighting``), f in
1/sr, compared in x = log(f + offset) (``passive_modes.LOG_OFFSET``).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .passive_modes import LOG_OFFSET
from .passive_prior import library_tables

#: Candidate k of ``choose_k``.
K_CANDIDATES = (1, 2, 3, 5, 8, 13, 20, 40)
#: Bounds of the fitted log slope: an exemplar may be up to 4x sharper or blunter, not inverted.
SLOPE_RANGE = (0.25, 4.0)


@dataclass(frozen=True, eq=False)
class ExemplarLibrary:
    """Log tables of a BRDF library, x = log(f + ``offset``), f in 1/sr.

    Attributes
    ----------
    x : ndarray (materials, 3, n_t n_s)
        Channel by channel, nodes flattened ``i * n_s + j``.
    grid : (int, int)
        (n_t, n_s).
    offset : float
        1/sr.
    k : int or None
        Exemplars averaged; None: chosen by ``choose_k`` for each fit's constrained nodes.
    """

    x: np.ndarray
    grid: tuple
    offset: float = LOG_OFFSET
    k: int | None = None

    @classmethod
    def from_brdfs(cls, brdfs, grid=(32, 32), *, k: int | None = None,
                   offset: float = LOG_OFFSET) -> "ExemplarLibrary":
        """Each member reduced as ``passive_prior.library_tables`` does.

        Raises
        ------
        ValueError
            Fewer than two materials, something not a BRDF, or a ``k`` not in [1, materials).
        """
        tables = library_tables(brdfs, grid)
        if k is not None and not (isinstance(k, (int, np.integer)) and 1 <= k < len(tables)):
            raise ValueError(f"k must be None or an int in [1, {len(tables) - 1}] for "
                             f"{len(tables)} materials, got {k!r}")
        if not (isinstance(offset, (int, float)) and offset > 0):
            raise ValueError(f"offset must be a number > 0 (1/sr), got {offset!r}")
        x = np.log(np.moveaxis(tables, -1, 1).reshape(len(tables), 3, -1) + offset)
        return cls(x, tuple(tables.shape[1:3]), float(offset), k)


@dataclass(frozen=True, eq=False)
class Exemplars:
    """The k library members nearest a recovered table.

    Attributes
    ----------
    index : ndarray (k,)
        Their rows in the library, nearest first.
    distance : ndarray (k,)
        Coverage-weighted RMS log difference at the constrained nodes after the fit.
    fitted : ndarray (k, 3, n)
        Their log tables with the fitted per-channel slope and offset applied.
    weights : ndarray (k,)
        Their weights in the average (inverse squared distance, sum 1).
    """

    index: np.ndarray
    distance: np.ndarray
    fitted: np.ndarray
    weights: np.ndarray

    def mean(self) -> np.ndarray:
        """(3, n) weighted mean of ``fitted``, log(f + offset)."""
        return np.einsum("k,kcn->cn", self.weights, self.fitted)


def nearest_exemplars(x, node_weights, library, k: int) -> Exemplars:
    """The ``k`` rows of ``library`` (M, 3, n) nearest the log table ``x`` (3, n) at the nodes
    with ``node_weights`` (n,) > 0, each fitted per channel as a x_m + b (a within
    ``SLOPE_RANGE``) in weighted least squares, weighted by inverse squared distance."""
    w = np.asarray(node_weights, float)
    sw = w.sum()
    mx = np.einsum("mcn,n->mc", library, w) / sw
    my = (x @ w) / sw
    dxm = library - mx[..., None]
    cov = np.einsum("mcn,cn,n->mc", dxm, x - my[:, None], w)
    var = np.einsum("mcn,mcn,n->mc", dxm, dxm, w)
    a = np.clip(cov / np.maximum(var, 1e-300), *SLOPE_RANGE)
    fitted = a[..., None] * dxm + my[None, :, None]
    dist = np.sqrt(np.einsum("mcn,n->m", (fitted - x) ** 2, w) / (3 * sw))
    order = np.argsort(dist)[:k]
    om = 1.0 / np.maximum(dist[order], 1e-12) ** 2
    return Exemplars(order, dist[order], fitted[order], om / om.sum())


def node_weights(coverage, constrained) -> np.ndarray:
    """(n,) weights of the nodes from ``Adequacy.coverage`` and ``Adequacy.constrained`` (n_t,
    n_s): the coverage, capped at a uniform sky's (1), on the constrained nodes; 0 elsewhere."""
    c = np.nan_to_num(np.asarray(coverage, float).ravel())
    return np.where(np.asarray(constrained).ravel(), np.minimum(c, 1.0), 0.0)


def choose_k(library, weights, candidates=K_CANDIDATES) -> int:
    """k by leave-one-out on ``library`` (M, 3, n) itself: each member's nodes with
    ``weights`` (n,) > 0 choose exemplars among the others, whose mean predicts its other
    nodes; the k of ``candidates`` (those below M) with the lowest RMS log error over all."""
    unseen = weights <= 0
    ks = [k for k in candidates if k < len(library)]
    sq = np.zeros(len(ks))
    for j in range(len(library)):
        others = np.delete(library, j, axis=0)
        ex = nearest_exemplars(library[j], weights, others, max(ks))
        for i, k in enumerate(ks):
            om = ex.weights[:k] / ex.weights[:k].sum()
            pred = np.einsum("k,kcn->cn", om, ex.fitted[:k, :, unseen])
            sq[i] += np.sum((pred - library[j][:, unseen]) ** 2)
    return ks[int(np.argmin(sq))]


def fill_unconstrained(f, coverage, constrained, library: ExemplarLibrary):
    """The recovered table ``f`` (n, 3), 1/sr, with the nodes outside ``constrained`` (n_t,
    n_s; ``Adequacy.constrained``) replaced by the mean of its nearest exemplars in ``library``
    (``library.k`` of them, or ``choose_k``'s), the distance weighted by ``coverage`` (n_t,
    n_s; ``Adequacy.coverage``). Returns (f (n, 3) >= 0, ``Exemplars``)."""
    w = node_weights(coverage, constrained)
    k = library.k if library.k is not None else choose_k(library.x, w)
    x = np.log(np.maximum(np.asarray(f, float), 0.0).T + library.offset)
    ex = nearest_exemplars(x, w, library.x, k)
    out = np.array(f, dtype=np.float64)
    unseen = w <= 0
    out[unseen] = np.maximum(np.exp(ex.mean()[:, unseen].T) - library.offset, 0.0)
    return out, ex
