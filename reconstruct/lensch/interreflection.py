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
    the peak test held it), ``weight[t, 0]`` x its material's lobes alone, ``lobes[labels[t], 0]``
    (Lafortune parameters (3, P) with rho_d 0), about that axis: f_r cos(theta_i) about the
    axis, 1/sr; with ``diffuse`` ((K, 3), ``SvbrdfOptions.interreflection_diffuse``) also
    ``weight[t, 1]`` x that colour's diffuse BRDF about the texel's input normal. (The lobe at several widths was tried and not kept: docs/diligent.md, round
    lensch9.)"""

    axes: np.ndarray
    weight: np.ndarray
    labels: np.ndarray
    lobes: np.ndarray
    diffuse: np.ndarray | None = None

    def predict(self, texel, wi, wo) -> np.ndarray:
        """(S, 3) for samples ``texel`` (S,), ``wi`` / ``wo`` (S, 3) in the input local frames."""
        values = held_extras(texel, wi, wo, self.axes, self.labels, self.lobes, self.diffuse)   # (S, E, 3)
        return np.einsum("se,sec->sc", self.weight[texel], values)


def held_extras(texel, wi, wo, axes, labels, lobes, diffuse=None) -> np.ndarray:
    """f cos (S, E, 3) of each sample under its texel's inter-reflection terms: its lobes
    ``lobes[labels]`` about its axis (:func:`axis_lobes`) and, where ``diffuse`` ((K, 3) a colour
    per material) is given, that colour's diffuse BRDF (1/pi) about the texel's input normal (local
    +z: the photometric-stereo normal its frame was built on, which the Lambertian reference
    uses), for the texels with an axis only; 0 below either horizon."""
    values = axis_lobes(texel, wi, wo, axes, labels, lobes)
    if diffuse is None:
        return values
    lit = np.isfinite(axes[texel, 0]) & (wi[:, 2] > 0) & (wo[:, 2] > 0)
    flat = diffuse[labels[texel]] * (np.where(lit, wi[:, 2], 0.0) / np.pi)[:, None]
    return np.concatenate([values, flat[:, None]], axis=1)


def axis_lobes(texel, wi, wo, axes, labels, lobes) -> np.ndarray:
    """f cos (S, E, 3) of each sample under each of its texel's lobes ``lobes[labels]``
    ((K, E, 3, P)) about its ``axes`` ((n, 3), input local frames; NaN: none, 0),
    0 where either direction is below the axis's horizon."""
    has = np.isfinite(axes[:, 0])
    frames = tangent_frames(np.where(has[:, None], axes, [0.0, 0.0, 1.0]))[texel]
    u, v = normalize(to_local(wi, frames)), normalize(to_local(wo, frames))
    seen = (u[:, 2] > 0) & (v[:, 2] > 0) & has[texel]
    t, z = lobe_geometry(u, v)
    K, E = lobes.shape[:2]
    return basis_values(t, z, np.where(seen, u[:, 2], 0.0), texel, labels, lobes, np.full(K, E, np.int64))

