"""The test zoo: reflectance made outside the repository's fitted models, for checking every
method on data it was not designed around.

- :func:`analytic_zoo`: lobes no fitted model expresses (``lobes.py``, and GGX with Smith
  masking and Schlick Fresnel over an Oren-Nayar body);
- :func:`measured_zoo`: the measured materials of a ``brdfs`` data folder (NBRDF fits of the
  MERL 100 and Nielsen 8 in ``nbrdf-merl/``, ``nbrdf-nielsen/``; RGL ``.bsdf`` files in
  ``rgl/``; MERL ``.binary`` files anywhere below), loaded on first use;
- :class:`NearestReciprocal`: how close any reciprocal model can come to a measured material
  that is not reciprocal (the RGL files are not, as Mitsuba evaluates them: docs/zoo.md).
"""
from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

from ..merl import read_merl
from .analytic import CookTorrance, OrenNayar
from .base import BRDF
from .dichromatic import Dichromatic
from .lobes import AshikhminShirley, RetroReflective, Sheen
from .nbrdf import load_nbrdf
from .rgl import read_rgl


def analytic_zoo() -> dict[str, BRDF]:
    """Name -> model of the analytic zoo members (sharp: the first two; smooth: the rest)."""
    return {
        "ashikhmin-shirley n=1000": AshikhminShirley(rd=(0.35, 0.25, 0.15), rs=0.05,
                                                     exponent=1000.0),
        "ggx a=0.08 over oren-nayar": Dichromatic(OrenNayar((0.5, 0.4, 0.3), 0.4),
                                                  CookTorrance(0.0, 0.04, 0.08, "ggx")),
        "retro-reflective": RetroReflective(),
        "sheen": Sheen(),
    }


#: sub-folder -> (file suffix, loader)
_KINDS = {"nbrdf-merl": (".npz", load_nbrdf), "nbrdf-nielsen": (".npz", load_nbrdf),
          "rgl": (".bsdf", read_rgl)}


def measured_files(root: str | os.PathLike) -> dict[str, Path]:
    """Name -> file of every measured material below ``root`` (names: ``merl/<stem>``,
    ``nielsen/<stem>``, ``rgl/<stem>``, ``merl-binary/<stem>``), sorted by name.

    Raises
    ------
    ValueError
        If ``root`` is not a folder or holds no measured material.
    """
    root = Path(root)
    if not root.is_dir():
        raise ValueError(f"measured BRDF folder {root} does not exist")
    found = {}
    for sub, (suffix, _) in _KINDS.items():
        for p in sorted((root / sub).glob(f"*{suffix}")):
            found[f"{sub.replace('nbrdf-', '')}/{p.stem}"] = p
    for p in sorted(root.rglob("*.binary")):
        found[f"merl-binary/{p.stem}"] = p
    if not found:
        raise ValueError(f"{root} holds no measured material (nbrdf-merl/*.npz, "
                         f"nbrdf-nielsen/*.npz, rgl/*.bsdf, *.binary)")
    return dict(sorted(found.items()))


def load_measured(path: str | os.PathLike) -> BRDF:
    """One measured material by its file type (``.npz`` NBRDF, ``.bsdf`` RGL, ``.binary`` MERL)."""
    suffix = Path(path).suffix
    loaders = {".npz": load_nbrdf, ".bsdf": read_rgl, ".binary": read_merl}
    if suffix not in loaders:
        raise ValueError(f"{path}: unknown measured-BRDF file type {suffix!r} "
                         f"(known: {sorted(loaders)})")
    return loaders[suffix](path)


def measured_zoo(root: str | os.PathLike, names=None) -> dict[str, BRDF]:
    """Name -> loaded model for the materials of :func:`measured_files` (all, or ``names``)."""
    files = measured_files(root)
    if names is not None:
        unknown = sorted(set(names) - set(files))
        if unknown:
            raise ValueError(f"{root}: no measured material named {unknown}")
        files = {n: files[n] for n in names}
    return {n: load_measured(p) for n, p in files.items()}


@dataclass(frozen=True, eq=False)
class NearestReciprocal(BRDF):
    """The reciprocal BRDF nearest to ``brdf`` in point-light radiance.

    At each direction pair (local frame, normal +z) it takes the value g minimising
    (cos theta_i (g - f(wi, wo)))^2 + (cos theta_o (g - f(wo, wi)))^2, the radiance errors of
    the pair lit from either side under unit irradiance:

        g = (cos^2 theta_i f(wi, wo) + cos^2 theta_o f(wo, wi)) / (cos^2 theta_i + cos^2 theta_o).

    A reciprocal model (a (theta_h, theta_d, phi_d mod pi) table, reflectance sharing's
    (u, v, w)) cannot tell the two orderings apart, so its images of a non-reciprocal material
    are this far off at best: the floor of such models. f_r in 1/sr, RGB.
    """

    brdf: BRDF

    def _evaluate(self, wi, wo):
        ci, co = wi[:, 2:3] ** 2, wo[:, 2:3] ** 2
        return (ci * self.brdf.evaluate(wi, wo) + co * self.brdf.evaluate(wo, wi)) / (ci + co)

    def take(self, index) -> "NearestReciprocal":
        return NearestReciprocal(self.brdf.take(index))
