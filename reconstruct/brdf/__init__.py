"""Reflectance models (see base.py for the conventions every model follows)."""
from .albedo import directional_albedo
from .analytic import (BlinnPhong, CookTorrance, ModifiedPhong, OrenNayar, Ward,
                       microfacet_distribution, smith_lambda)
from .base import BRDF, Lambertian
from .dichromatic import Dichromatic
from .lafortune import Lafortune
from .tabulated import Bivariate, TabulatedIsotropic

__all__ = ["BRDF", "Lambertian", "OrenNayar", "ModifiedPhong", "BlinnPhong", "Ward",
           "CookTorrance", "Lafortune", "Dichromatic", "TabulatedIsotropic", "Bivariate",
           "microfacet_distribution", "smith_lambda", "directional_albedo"]
