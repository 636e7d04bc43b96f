"""The light a mirror-like object reflects onto itself, as a second lobe per texel.

A mirror-like object that sees itself (DiLiGenT's goblet) shows, besides a light's highlight
about a texel's normal, the light's image in the object itself: a second highlight, as sharp,
about another axis. Lensch et al.'s per-texel BRDF about the texel's normal cannot express it,
and the normal fit follows it instead of the highlight (docs/diligent.md, rounds lensch6-8).
Where the peak test holds a texel's normal at its highlight, the normal its free fit found is
kept as the axis of that image, and the texel's material's lobes alone about it, with a
non-negative weight fitted with the projection (Sec. 8), are added to its prediction
(``SvbrdfOptions.interreflection_lobe``). It is light from the object, not a property of the
surface: :meth:`~reconstruct.lensch.SvbrdfFit.predict` adds it, the per-texel BRDFs
(:meth:`~reconstruct.lensch.SvbrdfFit.brdf`) do not hold it.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..frames import normalize, tangent_frames, to_local
from .lafortune_fit import lobe_geometry
from .projection import basis_values


@dataclass(frozen=True)
class Interreflection:
    """Per-texel inter-reflection lobes (``SvbrdfOptions.interreflection_lobe``): for texel t
    with a finite ``axes[t]`` (unit, its input local frame: the normal its free fit found before
    the peak test held it), the sum over widths e of ``weight[t, e]`` x its material's lobes at
    that width, ``lobes[labels[t], e]`` (Lafortune parameters (3, P) with rho_d 0; see
    :func:`widened`), about that axis: f_r cos(theta_i) about the axis, 1/sr."""

    axes: np.ndarray
    weight: np.ndarray
    labels: np.ndarray
    lobes: np.ndarray

    def predict(self, texel, wi, wo) -> np.ndarray:
        """(S, 3) for samples ``texel`` (S,), ``wi`` / ``wo`` (S, 3) in the input local frames."""
        values = axis_lobes(texel, wi, wo, self.axes, self.labels, self.lobes)   # (S, E, 3)
        return np.einsum("se,sec->sc", self.weight[texel], values)


def widened(lobes, factors) -> np.ndarray:
    """Lobes-alone parameters ``lobes`` (K, 3, P) at each exponent factor of ``factors`` (E,):
    (K, E, 3, P), each lobe's exponent N times the factor (f > 1 sharper: the angular width
    shrinks as 1/sqrt(f)) and its C_x, C_z scaled so that its value at normal incidence and
    exitance, |C_z|^N, stays the lobe's own (the weights then stay of one scale)."""
    f = np.asarray(factors, float)[None, :, None, None]
    out = np.repeat(lobes[:, None], f.shape[1], axis=1).astype(float)
    cz = np.maximum(np.abs(out[..., 2::3]), 1e-12)
    scale = cz ** (1.0 / f - 1.0)
    out[..., 1::3] *= scale
    out[..., 2::3] *= scale
    out[..., 3::3] *= f
    return out


def axis_lobes(texel, wi, wo, axes, labels, lobes) -> np.ndarray:
    """f cos (S, E, 3) of each sample under each of its texel's lobes ``lobes[labels]``
    ((K, E, 3, P): one per width) about its ``axes`` ((n, 3), input local frames; NaN: none, 0),
    0 where either direction is below the axis's horizon."""
    has = np.isfinite(axes[:, 0])
    frames = tangent_frames(np.where(has[:, None], axes, [0.0, 0.0, 1.0]))[texel]
    u, v = normalize(to_local(wi, frames)), normalize(to_local(wo, frames))
    seen = (u[:, 2] > 0) & (v[:, 2] > 0) & has[texel]
    t, z = lobe_geometry(u, v)
    K, E = lobes.shape[:2]
    return basis_values(t, z, np.where(seen, u[:, 2], 0.0), texel, labels, lobes, np.full(K, E, np.int64))

