"""How a mesh is textured: :class:`TextureConfig` and its :class:`Levelling` choice.

The conditions and steps the fields tune are described in :mod:`thermogrammetry.products.texture`.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..enums import StrChoice
from ..errors import ConfigError
from .._validate import config_keys
from .correction import CorrectionConfig

__all__ = ["Levelling", "TextureConfig"]


class Levelling(StrChoice):
    NONE = "none"
    OFFSETS = "offsets"



@dataclass(frozen=True)
class TextureConfig:
    """How a mesh is textured. Unknown keys in :meth:`from_dict` are errors."""

    texel_size_m: float | None = None  # None: half the median surface pixel size of the chosen images
    max_texture_px: int = 4096
    padding_texels: int = 2
    max_angle_deg: float = 75.0
    border_px: float = 2.0
    border_fraction: float = 0.1
    occlusion_tol_m: float = 0.02
    surface_tol_m: float = 0.05
    normal_tol_deg: float = 30.0
    clean_radius_px: int = 1
    # faces with no texel usable at clean_radius_px take texels usable at the largest smaller radius down to this one
    # (None: no fallback)
    min_clean_radius_px: int | None = None
    levelling: Levelling = Levelling.NONE
    offsets_max_pairs: int = 200_000
    correct: bool = False
    correction: CorrectionConfig = field(default_factory=CorrectionConfig)

    def __post_init__(self):
        object.__setattr__(self, "levelling", Levelling(self.levelling))
        if self.texel_size_m is not None and not (np.isfinite(self.texel_size_m) and self.texel_size_m > 0):
            raise ConfigError(f"TextureConfig.texel_size_m={self.texel_size_m!r}: expected a positive number of metres or None")
        if not 0 < self.max_angle_deg < 90:
            raise ConfigError(f"TextureConfig.max_angle_deg={self.max_angle_deg!r}: expected degrees in (0, 90)")
        if int(self.max_texture_px) < 64:
            raise ConfigError(f"TextureConfig.max_texture_px={self.max_texture_px!r}: expected at least 64")
        if self.min_clean_radius_px is not None and not (int(self.min_clean_radius_px) == self.min_clean_radius_px
                                                         and self.min_clean_radius_px >= 0):
            raise ConfigError(f"TextureConfig.min_clean_radius_px={self.min_clean_radius_px!r}: expected an integer >= 0 or None")
        for k in ("border_px", "occlusion_tol_m", "surface_tol_m"):
            if not getattr(self, k) >= 0:
                raise ConfigError(f"TextureConfig.{k}={getattr(self, k)!r}: expected a number >= 0")
        if isinstance(self.correction, dict):
            object.__setattr__(self, "correction", CorrectionConfig.from_dict(self.correction))

    @classmethod
    def from_dict(cls, d: dict) -> "TextureConfig":
        return cls(**config_keys(cls, d))
