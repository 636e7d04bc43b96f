"""The BRDF interface every reflectance model implements.

A model is a frozen dataclass whose fields are its parameters. Each parameter may be a scalar,
an RGB triple, or an array with a leading sample axis (N,) / (N, 3) for spatially varying
materials: parameters broadcast against the samples.

Directions are unit vectors in the local shading frame (z = surface normal), both pointing away
from the surface: ``wi`` towards the light, ``wo`` towards the viewer. ``evaluate`` returns the
BRDF value f_r in 1/sr, RGB, shape (N, 3), zero where either direction is below the surface.
Radiance from a point light is then ``f_r * cos(theta_i) * E``.

Every model can be split for polarisation-aware rendering: ``diffuse_part()`` (depolarising body
reflection) and ``specular_part()`` (polarisation-preserving interface reflection) are models
whose sum is the original.
"""
from __future__ import annotations

import abc
from dataclasses import dataclass, fields

import numpy as np


class BRDF(abc.ABC):
    """Base of the reflectance models (see module docstring for conventions)."""

    @abc.abstractmethod
    def _evaluate(self, wi: np.ndarray, wo: np.ndarray) -> np.ndarray:
        """Model formula for directions above the surface; (N, 3) or (N,) broadcastable to (N, 3)."""

    def evaluate(self, wi: np.ndarray, wo: np.ndarray) -> np.ndarray:
        """f_r(wi, wo) in 1/sr for local unit directions (N, 3) -> (N, 3) RGB."""
        wi = np.asarray(wi, dtype=np.float64).reshape(-1, 3)
        wo = np.asarray(wo, dtype=np.float64).reshape(-1, 3)
        if wi.shape != wo.shape:
            raise ValueError(f"wi and wo must have the same shape, got {wi.shape} and {wo.shape}")
        # rows below the horizon are zeroed below; their intermediate inf/NaN are expected
        with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
            f = np.broadcast_to(self._evaluate(wi, wo).reshape(len(wi), -1), (len(wi), 3))
        above = (wi[:, 2] > 0) & (wo[:, 2] > 0)
        return np.where(above[:, None], f, 0.0)

    __call__ = evaluate

    def defined(self, wi: np.ndarray, wo: np.ndarray) -> np.ndarray:
        """Where the model has a value, (N,) bool: both directions above the surface (a table
        also needs a measured node nearby, see ``TabulatedIsotropic``). Elsewhere ``evaluate``
        returns 0, which is "unknown", not "black"."""
        wi = np.asarray(wi, dtype=np.float64).reshape(-1, 3)
        wo = np.asarray(wo, dtype=np.float64).reshape(-1, 3)
        return (wi[:, 2] > 0) & (wo[:, 2] > 0)

    def diffuse_part(self) -> "BRDF":
        """The body (depolarising) reflection of this model; default: none (black)."""
        return Lambertian(0.0)

    def specular_part(self) -> "BRDF":
        """The interface (polarisation-preserving) reflection; default: the whole model."""
        return self

    def take(self, index: np.ndarray) -> "BRDF":
        """The same model with per-sample parameters indexed by ``index`` (spatial variation)."""
        kw = {}
        for f in fields(self):  # type: ignore[arg-type]
            v = getattr(self, f.name)
            arr = np.asarray(v) if not isinstance(v, (str, bool)) else v
            kw[f.name] = arr[index] if isinstance(arr, np.ndarray) and arr.ndim >= 1 and \
                arr.shape[0] > 3 else v
        return type(self)(**kw)


def rgb(value, n_extra_dims: int = 0) -> np.ndarray:
    """A parameter as an array broadcastable to (N, 3): scalar -> (1, 1); (3,) -> (1, 3); (N,) -> (N, 1)."""
    a = np.asarray(value, dtype=np.float64)
    if a.ndim == 0:
        return a.reshape(1, 1)
    if a.ndim == 1:
        return a.reshape(1, 3) if a.shape[0] == 3 else a.reshape(-1, 1)
    return a


def check_param(owner: str, name: str, value, *, low: float | None = 0.0,
                high: float | None = None, low_open: bool = False) -> None:
    """Raise ``ValueError`` naming ``owner.name`` unless ``value`` is finite and within bounds.

    ``low``/``high`` are inclusive unless ``low_open`` (strictly greater than ``low``).
    """
    a = np.asarray(value, dtype=np.float64)
    if not np.all(np.isfinite(a)):
        raise ValueError(f"{owner}.{name} must be finite, got non-finite values")
    if a.size == 0:
        raise ValueError(f"{owner}.{name} is empty")
    if low is not None and (np.any(a <= low) if low_open else np.any(a < low)):
        rel = ">" if low_open else ">="
        raise ValueError(f"{owner}.{name} must be {rel} {low}, got minimum {a.min():g}")
    if high is not None and np.any(a > high):
        raise ValueError(f"{owner}.{name} must be <= {high}, got maximum {a.max():g}")


def scalar(value) -> np.ndarray:
    """A scalar parameter as an array broadcastable to (N,): scalar -> (1,); (N,) stays."""
    return np.asarray(value, dtype=np.float64).reshape(-1)


@dataclass(frozen=True)
class Lambertian(BRDF):
    """Ideal diffuse reflector, f_r = albedo / pi.

    Parameters
    ----------
    albedo : float, (3,), (N,) or (N, 3)
        Diffuse reflectance (RGB), >= 0; <= 1 for a physical (energy-conserving) surface.

    References
    ----------
    J. H. Lambert, "Photometria", 1760.
    """

    albedo: object = 0.5

    def __post_init__(self):
        check_param("Lambertian", "albedo", self.albedo)

    def _evaluate(self, wi, wo):
        return np.broadcast_to(rgb(self.albedo) / np.pi, (len(wi), 3))

    def diffuse_part(self) -> "BRDF":
        return self

    def specular_part(self) -> "BRDF":
        return Lambertian(0.0)
