"""Neural BRDF fits of measured materials (NBRDF, Sztrajman et al. 2021), evaluated with numpy.

Each material is a 6-21-21-3 multilayer perceptron stored as a ``.npz`` of ``W1 (6, 21)``,
``b1``, ``W2 (21, 21)``, ``b2``, ``W3 (21, 3)``, ``b3``. Its input is the halfway vector turned
to phi_h = 0 and the Rusinkiewicz difference vector, ``x = (sin th_h, 0, cos th_h, d_x, d_y,
d_z)``; its output, after ``exp(.) - 1`` clamped at 0, is f_r in 1/sr, linear RGB with the MERL
channel scales applied (the networks were trained on MERL-format tables).

References
----------
A. Sztrajman, G. Rainer, T. Ritschel, T. Weyrich, "Neural BRDF representation and importance
sampling", Computer Graphics Forum 40(6), 2021 (weights: asztr/Neural-BRDF).
"""
from __future__ import annotations

import os
from dataclasses import dataclass

import numpy as np

from ..coords import halfway_difference
from .base import BRDF

_LAYERS = {"W1": (6, 21), "b1": (21,), "W2": (21, 21), "b2": (21,), "W3": (21, 3), "b3": (3,)}


@dataclass(frozen=True, eq=False)
class NeuralBRDF(BRDF):
    """A measured isotropic material as its NBRDF network (see module docstring).

    Parameters
    ----------
    weights : dict of str -> ndarray
        ``W1 b1 W2 b2 W3 b3`` with the shapes of ``_LAYERS`` (float32 as stored).
    reciprocal : bool
        Average f(wi, wo) and f(wo, wi): the fits are not exactly reciprocal (about 3 % apart
        on a matte paint, more near grazing), a measured BRDF is. False gives the raw network.
    name : str
        The material (file stem), for tables and plots.
    """

    weights: dict
    reciprocal: bool = True
    name: str = "nbrdf"

    def __post_init__(self):
        for key, shape in _LAYERS.items():
            w = self.weights.get(key)
            if w is None or np.shape(w) != shape or not np.all(np.isfinite(w)):
                raise ValueError(f"NeuralBRDF {self.name!r}: weight {key} must be finite with "
                                 f"shape {shape}, got "
                                 f"{'nothing' if w is None else np.shape(w)}")

    def _network(self, wi, wo) -> np.ndarray:
        theta_h, _, theta_d, phi_d = halfway_difference(wi, wo)
        st_d = np.sin(theta_d)
        x = np.stack([np.sin(theta_h), np.zeros_like(theta_h), np.cos(theta_h),
                      st_d * np.cos(phi_d), st_d * np.sin(phi_d), np.cos(theta_d)], axis=1)
        w = self.weights
        a = np.maximum(x.astype(np.float32) @ w["W1"] + w["b1"], 0.0)
        a = np.maximum(a @ w["W2"] + w["b2"], 0.0)
        return np.maximum(np.expm1((a @ w["W3"] + w["b3"]).astype(np.float64)), 0.0)

    def _evaluate(self, wi, wo):
        f = self._network(wi, wo)
        return 0.5 * (f + self._network(wo, wi)) if self.reciprocal else f

    def take(self, index) -> "NeuralBRDF":
        return self


def load_nbrdf(path: str | os.PathLike, *, reciprocal: bool = True) -> NeuralBRDF:
    """Read an NBRDF ``.npz`` (module docstring); the material is named after the file stem.

    Raises
    ------
    ValueError
        If the file lacks a layer or a layer has the wrong shape (naming the file and layer).
    """
    path = os.fspath(path)
    with np.load(path) as data:
        missing = sorted(set(_LAYERS) - set(data.files))
        if missing:
            raise ValueError(f"{path}: not an NBRDF file, missing arrays {missing}")
        weights = {k: np.asarray(data[k], dtype=np.float32) for k in _LAYERS}
    name = os.path.splitext(os.path.basename(path))[0]
    try:
        return NeuralBRDF(weights, reciprocal, name)
    except ValueError as err:
        raise ValueError(f"{path}: {err}") from None
