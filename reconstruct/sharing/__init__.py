"""Reflectance sharing (Zickler et al. 2005): RBF interpolation in the joint spatial/angular domain."""
from .rbf import RbfFit, RbfModel, SharingError, fit_rbf

__all__ = ["RbfFit", "RbfModel", "SharingError", "fit_rbf"]
