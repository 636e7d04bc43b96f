"""Reflectance sharing (Zickler et al. 2005): non-parametric BRDFs and spatially varying BRDFs
as linear-RBF interpolants in the joint spatial/angular domain (x, y, u, v, w).

- :func:`fit_rbf` / :class:`RbfModel`: the interpolant and greedy centre selection (``rbf.py``);
- :func:`fit_isotropic`: the homogeneous fit (``isotropic.py``: log-domain values, w scale
  chosen on held-out images, reciprocal unless :func:`check_reciprocity` finds the samples'
  two orderings of a pair disagree, ``reciprocity.py``); :func:`fit_spatial`: the spatially varying, dichromatic and
  single-image fits (``fits.py``); both give ``BRDF`` models (``models.py``);
  :func:`fit_spatial_blocks`: the dichromatic fit over texel blocks, its per-texel steps one
  block at a time and the RBFs on a stated subsample of texels (``blocks.py``);
- :func:`photometric_normals`: per-texel normals from the diffuse samples, the geometry the fits
  need where a mesh lacks the surface's relief (``normals.py``; ``fit_spatial(fit_normals=True)``);
- :func:`samples_from_images`: reflectance samples from images under distant lights;
- baselines for the paper's comparisons (``baselines.py``).
"""
from .blocks import FIT_TEXELS, fit_spatial_blocks
from .fits import SpatialFit, fit_spatial, group_median
from .isotropic import IsotropicFit, ScaleChoice, fit_isotropic
from .models import ANGULAR_WEIGHT, ASYMMETRY_WEIGHT, RbfBRDF, SpatialRbfBRDF, polar_points
from .normals import PhotometricNormals, photometric_normals, reframe
from .rbf import RbfFit, RbfModel, SharingError, fit_rbf
from .reciprocity import RECIPROCITY_TOLERANCE, ReciprocityCheck, check_reciprocity
from .samples import ImageSamples, samples_from_images

__all__ = ["RbfFit", "RbfModel", "SharingError", "fit_rbf", "IsotropicFit", "SpatialFit",
           "fit_isotropic", "ScaleChoice", "fit_spatial", "fit_spatial_blocks", "FIT_TEXELS", "group_median", "RbfBRDF",
           "SpatialRbfBRDF", "ANGULAR_WEIGHT", "ASYMMETRY_WEIGHT", "polar_points",
           "ReciprocityCheck", "check_reciprocity", "RECIPROCITY_TOLERANCE",
           "ImageSamples", "samples_from_images", "PhotometricNormals", "photometric_normals",
           "reframe"]
