"""Spatially varying BRDFs and normal maps after Lensch et al. 2003 (ACM TOG 22(2)).

Lafortune fits with covariance (Sec. 6), split-recluster-fit clustering (Sec. 7), projection
into per-cluster bases with optional principal function analysis (Sec. 8), normal fitting
(Sec. 9), on the lumitexels of :mod:`reconstruct.lumitexels`.
"""
from .lafortune_fit import LafortuneFit, LafortuneFitError, fit_lafortune
from .options import SvbrdfError, SvbrdfOptions
from .svbrdf import RMS_COLUMNS, SvbrdfFit, fit_svbrdf, fit_svbrdf_blocks, fit_svbrdf_lumitexels
from .texel_blocks import ArrayBlocks, SampleBlock, TexelBlocks

__all__ = ["fit_lafortune", "LafortuneFit", "LafortuneFitError", "fit_svbrdf", "fit_svbrdf_blocks",
           "fit_svbrdf_lumitexels", "TexelBlocks", "ArrayBlocks", "SampleBlock", "SvbrdfFit", "SvbrdfError", "SvbrdfOptions", "RMS_COLUMNS"]
