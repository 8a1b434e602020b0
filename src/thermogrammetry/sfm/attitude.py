"""Camera attitudes from DJI gimbal angles: moved to :mod:`thermogrammetry.geometry.attitude` (pure geometry, used
by ``synthetic`` below ``sfm``); this module keeps the old import path."""

from ..geometry.attitude import *  # noqa: F401,F403
from ..geometry.attitude import __all__  # noqa: F401
