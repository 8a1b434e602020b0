"""Dense matching of oriented thermal frames: rectification, semi-global matching, multi-view depth fusion.

- :func:`disparity` — disparity of a rectified pair (full dynamic range of 16-bit/float frames);
- :mod:`.rectify` — epipolar rectification with our camera model (distortion included);
- :mod:`.fusion` — pair selection by overlap and base/height ratio, depth maps, geometric consistency;
- the ``dense`` verb over a survey folder (cloud + DSM, tiles, tasks) is :mod:`thermogrammetry.pipeline.dense`.
"""

from __future__ import annotations

from .stereo import disparity

__all__ = ["disparity"]
