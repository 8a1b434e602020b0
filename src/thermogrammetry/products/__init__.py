"""Products whose values stay temperatures: per-pixel correction, DSM gridding, point clouds, orthophotos.

Submodules are imported lazily (``thermogrammetry.products.X`` loads only what it names):

- :mod:`.correction` — the per-pixel viewing-angle / emissivity / transmission correction (seed 000),
  the one implementation that ``closerange``, ``correct`` and ``ortho`` call;
- :mod:`.surfaces` — per-pixel geometry against a mesh or a DSM;
- :mod:`.raster` — GeoTIFF (COG) writing and reading; :mod:`.dsm` — DSM gridding in tiles;
- :mod:`.cloud` — LAS/PLY point clouds with ``temperature_k``; :mod:`.ortho` — true orthophoto mosaics;
- :mod:`.evaluate` — DSM and check-point statistics;
- :mod:`.texture` — thermal textures of meshes (best image per face, occlusion, source map),
  :mod:`.texture_export` — GLB/OBJ/PLY/TIFF of a texture; :mod:`.facade` — facade mosaics without a mesh.
"""

from __future__ import annotations

import importlib

_LAZY = {
    "CorrectionConfig": "correction",
    "CorrectionResult": "correction",
    "apply_correction": "correction",
    "correct_oriented_image": "correction",
    "camera_rays": "correction",
    "dsm_to_mesh": "surfaces",
    "mesh_rasters": "surfaces",
    "TextureConfig": "texture",
    "TextureView": "texture",
    "texture_mesh": "texture",
    "thermal_poses_from_rig": "texture",
}

__all__ = sorted(_LAZY)


def __getattr__(name):
    mod = _LAZY.get(name)
    if mod is None:
        raise AttributeError(f"module 'thermogrammetry.products' has no attribute {name!r}")
    return getattr(importlib.import_module(f".{mod}", __name__), name)
