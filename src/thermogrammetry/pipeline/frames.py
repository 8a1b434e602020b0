"""The oriented thermal frames of a survey folder, as the verbs that read a survey (dense, ortho) see them.

A ``survey`` folder holds ``cameras.json`` (schema :mod:`thermogrammetry.io.oriented`), the decoded frames it
names and, for 8-bit frames with a burned-in camera display, ``work/overlay.json`` with the display's mask.
:class:`SurveyFrames` reads them with a small frame cache; :func:`open_survey` keeps one per worker process for
the tasks of a run.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..errors import ConfigError, DataFileError

__all__ = ["SurveyFrames", "open_survey"]


class SurveyFrames:
    """The oriented thermal images of a survey folder with a small frame cache (callable index → frame).

    ``dji_sdk``: DJI's Thermal SDK library (or ``$THERMOGRAMMETRY_DJI_TSDK``). When the survey's frames are raw
    counts decoded from DJI R-JPEGs (``cameras.json`` names each frame's source file), the frames are read again
    from those files through the SDK, in kelvin (``unit`` ``"K"``): the products are temperatures without a new
    survey. A path given explicitly for frames that are not counts of DJI R-JPEGs is refused.
    """

    def __init__(self, survey_dir, cache: int = 12, dji_sdk: str | None = None):
        from ..io.oriented import OrientedCameras

        self.root = Path(survey_dir)
        self.oc = OrientedCameras.load(self.root)
        self.images = [im for im in self.oc.images if im.frame is not None and im.sensor.value == "thermal"]
        if len(self.images) < 3:
            raise DataFileError(f"{self.root / 'cameras.json'}: {len(self.images)} oriented thermal image(s) with a "
                                "decoded frame; expected at least 3 for dense matching")
        units = sorted({im.unit.value for im in self.images})
        if len(units) != 1:
            raise DataFileError(f"{self.root / 'cameras.json'}: frames of mixed units {units}; expected one unit")
        self.unit = units[0]
        self.names = [im.name for im in self.images]
        self.cameras = [self.oc.camera_of(im) for im in self.images]
        self.poses = [(im.R, im.t) for im in self.images]
        self.crs = self.oc.crs
        self._cache: dict[int, np.ndarray] = {}
        self._max = int(cache)
        self._display = self._load_display_mask()
        self.dji_sdk = self._sdk_sources(dji_sdk)

    def _sdk_sources(self, dji_sdk) -> str | None:
        """The SDK path when the frames are to be read again from their DJI R-JPEGs through it, else None."""
        from ..io.dji_sdk import check_dji_sdk, sdk_path

        sdk = sdk_path(dji_sdk)
        if sdk is None:
            return None
        if dji_sdk is not None:
            check_dji_sdk(sdk)
        if self.unit != "counts":
            if dji_sdk is not None:
                raise ConfigError(f"--dji-sdk {dji_sdk}: the frames of {self.root} are {self.unit!r}, not raw counts of "
                                  "DJI R-JPEGs (the SDK has nothing to convert); leave --dji-sdk out")
            return None
        from ..io.thermal import sniff_reader

        bad = []
        for im in self.images:
            src = Path(im.source) if im.source else None
            try:
                ok = src is not None and src.is_file() and sniff_reader(src).name == "dji_rjpeg"
            except (OSError, ValueError):
                ok = False
            if not ok:
                bad.append(f"{im.name} ({im.source or 'no source recorded'})")
        if bad:
            if dji_sdk is None:
                return None
            raise ConfigError(f"--dji-sdk {dji_sdk}: {len(bad)} frame(s) of {self.root / 'cameras.json'} do not come from a "
                              f"DJI R-JPEG that is still in place, e.g. {bad[0]}; expected the survey of DJI R-JPEGs "
                              "with the files where the survey read them")
        check_dji_sdk(sdk)
        self.unit = "K"
        return sdk

    def _load_display_mask(self):
        """The mask of a camera display burned into the survey's 8-bit frames (``survey`` found it:
        ``work/overlay.json``, ``features/overlay.npz``), or None."""
        import json

        info = self.root / "work" / "overlay.json"
        if self.unit != "dn" or not info.is_file():
            return None
        try:
            ov = json.loads(info.read_text())
            if not ov.get("found"):
                return None
            with np.load(self.root / ov["key"]) as z:
                return np.asarray(z["mask"], bool)
        except (OSError, ValueError, KeyError) as exc:
            raise DataFileError(f"{info}: a burned-in display is recorded but its mask cannot be read ({exc})") from None

    def display_mask(self, i: int) -> np.ndarray | None:
        """(H, W) bool: the pixels of image ``i`` that a camera display covers (never a source of values), or None."""
        m = self._display
        if m is None:
            return None
        W, H = self.cameras[i].image_size
        return m if m.shape == (H, W) else None

    def __len__(self) -> int:
        return len(self.images)

    def __call__(self, i: int) -> np.ndarray:
        if i not in self._cache:
            if self.dji_sdk is not None:
                from ..io.thermal import read_thermal

                a = np.asarray(read_thermal(self.images[i].source, dji_sdk=self.dji_sdk).require_temperature(), np.float32)
            else:
                a = self.oc.read_frame(self.images[i])
            cam = self.cameras[i]
            if a.shape[:2] != (cam.image_size[1], cam.image_size[0]):
                raise DataFileError(f"{self.oc.frame_path(self.images[i])}: frame is {a.shape[1]}x{a.shape[0]} px; "
                                    f"camera {self.images[i].camera_id!r} expects {cam.image_size[0]}x{cam.image_size[1]}")
            if len(self._cache) >= self._max:
                self._cache.pop(next(iter(self._cache)))
            self._cache[i] = a
        return self._cache[i]


_WORKER_SURVEYS: dict[str, SurveyFrames] = {}


def open_survey(path: str, dji_sdk: str | None = None) -> SurveyFrames:
    """The :class:`SurveyFrames` of ``path``, kept for the next task of the same worker process (one survey at a time)."""
    key = f"{path}\0{dji_sdk or ''}"
    if key not in _WORKER_SURVEYS:
        _WORKER_SURVEYS.clear()
        _WORKER_SURVEYS[key] = SurveyFrames(path, dji_sdk=dji_sdk)
    return _WORKER_SURVEYS[key]
