"""Importers: image sets recorded elsewhere become sessions of the store, with their provenance.

- :mod:`.diligent`: multi-light photometric-stereo sets in the DiLiGenT layout (Shi et al. 2016).
"""
from .diligent import (DiligentFormatError, MultiLightSet, import_diligent, read_diligent,
                       read_imported_session)

__all__ = ["DiligentFormatError", "MultiLightSet", "import_diligent", "read_diligent",
           "read_imported_session"]
