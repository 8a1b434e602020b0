"""Changes of a synthetic scene between two flights: a building's roof warmed by a given amount.

The scene's true surface temperature is the field ``Terrain.temperature_k`` (:func:`.terrain.make_terrain`: the
material's base temperature, a smooth field, a fine texture and the roofs' hot vents) that every frame is rendered
from; a change between two flights is that field with a patch added (:func:`warm_roof`), the geometry, the
materials and the flight plan unchanged. The rendered apparent change is smaller than the kinetic one by the
roof's emissivity (and the atmosphere's transmission): the frames see ``ε · ΔS`` of the Planck signal.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from ..errors import ConfigError

__all__ = ["building_footprint", "warm_roof"]


def building_footprint(terrain, index: int, x=None, y=None, *, grow_m: float = 0.0) -> np.ndarray:
    """Whether local points (x, y) lie on building ``index``'s roof (its rectangle grown by ``grow_m``, m; negative:
    shrunk). Without ``x, y``: the terrain's texture cells (the grid of ``temperature_k``).

    Parameters
    ----------
    terrain : :class:`~thermogrammetry.synthetic.terrain.Terrain`
    index : into ``terrain.buildings``
    x, y : local coordinates (m, any shape), or None
    """
    if not 0 <= index < len(terrain.buildings):
        raise ConfigError(f"building {index}: the scene has {len(terrain.buildings)} building(s)")
    b = terrain.buildings[index]
    if x is None:
        ct = terrain.texture_cell_m
        h, w = terrain.temperature_k.shape
        x, y = np.meshgrid((np.arange(w) + 0.5) * ct, terrain.height_m - (np.arange(h) + 0.5) * ct)
    x, y = np.asarray(x, float), np.asarray(y, float)
    ca, sa = np.cos(b["angle"]), np.sin(b["angle"])
    u = (x - b["cx"]) * ca + (y - b["cy"]) * sa
    v = -(x - b["cx"]) * sa + (y - b["cy"]) * ca
    return (np.abs(u) <= b["w"] / 2 + grow_m) & (np.abs(v) <= b["l"] / 2 + grow_m)


def warm_roof(scene, index: int, delta_k: float):
    """A copy of a :class:`~thermogrammetry.synthetic.survey.SurveyScene` whose building ``index`` has its roof's
    surface temperature raised by ``delta_k`` (K) everywhere on it; the original scene is unchanged."""
    ter = scene.terrain
    t = ter.temperature_k + np.float32(delta_k) * building_footprint(ter, index)
    return dataclasses.replace(scene, terrain=dataclasses.replace(ter, temperature_k=t.astype(np.float32)))
