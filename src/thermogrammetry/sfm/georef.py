"""Georeferencing and the final adjustment of an oriented block: GNSS, GCPs, check points.

1. **Start**: a similarity (Umeyama 1991) from the model's projection centres to the GNSS positions
   (>= 3 images, not collinear), else from the triangulated GCPs to their coordinates (>= 3 GCPs).
2. **Final bundle adjustment** on the engine with GNSS camera-centre priors (σ per image, lever arm in the
   camera frame) and weighted GCPs (σ per coordinate, their image measurements with σ in px); the camera
   is self-calibrated (the named parameters free) unless a calibrated camera was given. A first robust
   (Huber) solve finds blunders: tie observations above ``max_error_px`` and GCP measurements above
   ``max(gcp_reject_px, 5 σ)`` are removed (a GCP measured in an image where it cannot be seen ends
   here, reported by image and id); the second, unweighted-loss solve gives σ0, the a-posteriori
   covariance of every camera parameter and pose, and the residuals.
3. **Check points never enter the adjustment**: each is intersected afterwards from its image
   measurements with the adjusted cameras, and its covariance is the propagation of both the measurement
   noise and the a-posteriori covariance of the poses and intrinsics involved::

       Σ_X = N⁻¹ + G Σ_θ Gᵀ,   N = J_Xᵀ W J_X,   G = N⁻¹ J_Xᵀ W J_θ

   (J by central differences in the engine's parameterisation: left rotation increment about the
   camera axes, projection centre, camera parameters).

The steps are in :mod:`.georef_control` (:class:`ControlInputs`, :class:`Datum`), :mod:`.georef_datum` (the
similarity start), :mod:`.georef_gnss` (GNSS offset, misfit and consensus), :mod:`.georef_adjustment` (the
final adjustment) and :mod:`.georef_checks` (check points, accuracy statistics); every name is importable
from this module as before.

References
----------
Umeyama, S. (1991). Least-squares estimation of transformation parameters between two point patterns.
IEEE PAMI 13(4), 376-380.
Khodaei, B., Samadzadegan, F., Dadras Javan, F., Hasani, H. (2015). 3D surface generation from aerial
thermal imagery (GCPs for absolute orientation, check points, Table 3 accuracy layout).
Förstner, W., Wrobel, B. P. (2016). Photogrammetric Computer Vision, §4.2.4 (propagation), §15.4.
"""

from __future__ import annotations

# the names live in georef_control (inputs, datum), georef_datum (the similarity start), georef_gnss (GNSS
# offset, misfit, consensus), georef_adjustment (the final adjustment) and georef_checks (check points,
# statistics); every name importable from this module before stays importable here
from .georef_adjustment import (
    HUBER_K,  # noqa: F401  (importable from here as before)
    MIN_FINAL_TRI_ANGLE_DEG,  # noqa: F401  (importable from here as before)
    FinalAdjustment,
    final_adjustment,
    parallel_ray_points,
)
from .georef_checks import axis_statistics, intersect_check_points
from .georef_control import ControlInputs, Datum, DatumSource
from .georef_datum import (
    ATTITUDE_MAX_DISAGREEMENT_DEG,  # noqa: F401  (importable from here as before)
    COLLINEAR_SIGMA,  # noqa: F401  (importable from here as before)
    MIN_ATTITUDE_IMAGES,  # noqa: F401  (importable from here as before)
    apply_similarity,
    attitude_images,  # noqa: F401  (importable from here as before)
    collinear,
    similarity_start,
)
from .georef_gnss import (
    GNSS_CONSENSUS_SIGMA,  # noqa: F401  (importable from here as before)
    GNSS_CONSENSUS_SPREAD,  # noqa: F401  (importable from here as before)
    GNSS_OFFSET_MIN_GCPS,  # noqa: F401  (importable from here as before)
    GNSS_REJECT_SIGMA,  # noqa: F401  (importable from here as before)
    GnssConsensus,  # noqa: F401  (importable from here as before)
    GnssOffset,
    gnss_consensus,  # noqa: F401  (importable from here as before)
    gnss_misfit,  # noqa: F401  (importable from here as before)
    gnss_offset,
)

__all__ = ["Datum", "DatumSource", "GnssOffset", "gnss_offset", "ControlInputs", "FinalAdjustment", "similarity_start", "apply_similarity", "final_adjustment",
           "intersect_check_points", "axis_statistics"]

#: old private names, still imported from here (tests/test_tracks.py)
_collinear = collinear
_parallel_ray_points = parallel_ray_points
