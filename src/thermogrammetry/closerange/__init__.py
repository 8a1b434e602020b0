"""Seed 000's close-range workflow: optical cameras by DLT, pass points, the thermal camera from pass
points only, planes by marked points, and per-pixel directional correction with precision.

Array-level API (pure functions, no paths):

- :func:`solve_network` (:mod:`.solve`) — the sequential orientation chain with a global linear error
  propagation; :func:`adjust_network` (:mod:`.adjust`) — optional joint adjustment with additional
  parameters;
- :func:`estimate_planes`, :func:`correct_thermal_image` (:mod:`.workflow`) — planes (eq. 5–6) and the
  per-pixel correction (eq. 7–8, directional emissivity, transmission) with valid mask and uncertainty;
- :func:`correct_oriented_image` — the general case (any oriented camera, planes / mesh / DSM);
- :func:`closerange_steps` (:mod:`.pipeline`) — the workflow as pipeline steps over a project store.

References
----------
Sawicki P., Stein R., Więcek B., *Directional emissivity correction by photogrammetric 3D object
reconstruction* (seed 000). Abdel-Aziz Y.I., Karara H.M. (1971), DLT.
"""

from __future__ import annotations

from .adjust import adjust_network
from .pipeline import closerange_steps, write_inputs
from .solve import NetworkResult, Observations, solve_network
from .workflow import (
    CloseRangeConfig,
    CorrectionResult,
    correct_oriented_image,
    correct_thermal_image,
    estimate_planes,
)

__all__ = [
    "Observations",
    "NetworkResult",
    "solve_network",
    "adjust_network",
    "CloseRangeConfig",
    "CorrectionResult",
    "estimate_planes",
    "correct_thermal_image",
    "correct_oriented_image",
    "closerange_steps",
    "write_inputs",
]
