"""Reflectance models (see base.py for the conventions every model follows)."""
from .base import BRDF, Lambertian

__all__ = ["BRDF", "Lambertian"]
