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

    Parameters
    ----------
    survey_dir : the survey folder (``cameras.json`` in it)
    cache : frames kept in memory
    dji_sdk : DJI's Thermal SDK library (or ``$THERMOGRAMMETRY_DJI_TSDK``). When the survey's frames are raw
        counts decoded from DJI R-JPEGs (``cameras.json`` names each frame's source file), the frames are read again
        from those files through the SDK, in kelvin (``unit`` ``"K"``): the products are temperatures without a new
        survey. A path given explicitly for frames that are not counts of DJI R-JPEGs is refused.
    need : the fewest usable images the verb works with (dense 3, ortho 1)
    verb : names the verb in the messages
    check : decode every frame once before any work (:meth:`_check_frames`): a frame that does not decode, is missing
        or has another size than its camera is skipped by name (``skipped``); a frame whose dtype or bands contradict
        its declared unit is refused
    skip : names to leave out without checking (the ``skipped`` of the checked instance, for the worker processes)
    """

    def __init__(self, survey_dir, cache: int = 12, dji_sdk: str | None = None, *, need: int = 3, verb: str = "dense",
                 check: bool = True, skip: tuple[str, ...] = ()):
        from ..io.oriented import OrientedCameras

        self.root = Path(survey_dir)
        self.oc = OrientedCameras.load(self.root)
        where = self.root / "cameras.json"
        thermal = [im for im in self.oc.images if im.sensor.value == "thermal"]
        with_frame = [im for im in thermal if im.frame is not None]
        if len(with_frame) < need:
            raise DataFileError(f"{where}: {len(with_frame)} oriented thermal image(s) with a decoded frame "
                                f"({len(self.oc.images)} image(s) in the file, {len(thermal)} thermal); {verb} needs at "
                                f"least {need}")
        units = sorted({im.unit.value for im in with_frame})
        if len(units) != 1:
            raise DataFileError(f"{where}: frames of mixed units {units}; expected one unit")
        self.unit = units[0]
        self.skipped: list[tuple[str, str]] = []
        skip = set(skip)
        self.images = [im for im in with_frame if im.name not in skip]
        if check:
            self._check_frames()
        if len(self.images) < need:
            listed = "; ".join(f"{n}: {r}" for n, r in self.skipped[:5]) + (" ..." if len(self.skipped) > 5 else "")
            raise DataFileError(f"{where}: {len(self.images)} usable frame(s) of {len(with_frame)}; {verb} needs at "
                                f"least {need} (skipped: {listed or 'none'})")
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

    def _check_frames(self) -> None:
        """Decode every frame once: skip the unreadable ones by name, refuse a dtype/bands that contradict the unit."""
        from ..errors import ConfigError

        keep = []
        for k, im in enumerate(self.images):
            try:
                a = self.oc.read_frame(im)
            except DataFileError as exc:
                self.skipped.append((im.name, str(exc)))
                continue
            p = self.oc.frame_path(im)
            bands = 1 if a.ndim == 2 else (a.shape[2] if a.ndim == 3 else 0)
            desc = f"{a.dtype} {bands}-band" + (" (colour)" if bands >= 3 else "")
            which = f"cameras.json image {im.name!r} (unit {im.unit.value!r})"
            if bands == 0:
                self.skipped.append((im.name, f"{p}: a {a.ndim}-D array of shape {a.shape}; expected an image"))
                continue
            if im.unit.value == "K" and (a.dtype.kind != "f" or bands != 1):
                raise ConfigError(f"{p}: a {desc} frame, but {which} declares kelvin; expected a float single-band "
                                  "frame of temperatures in K (or the unit 'dn' for an 8-bit rendering, 'counts' for raw "
                                  "sensor counts)")
            if im.unit.value == "counts" and (a.dtype.kind not in "ui" or bands != 1):
                raise ConfigError(f"{p}: a {desc} frame, but {which} declares raw sensor counts; expected an integer "
                                  "single-band frame (or the unit 'K' for float kelvin frames)")
            if im.unit.value == "dn" and a.dtype.kind not in "ui":
                raise ConfigError(f"{p}: a {desc} frame, but {which} declares display numbers; expected 8- or 16-bit "
                                  "integers (or the unit 'K' for float kelvin frames)")
            W, H = self.oc.camera_of(im).image_size
            if a.shape[:2] != (H, W):
                self.skipped.append((im.name, f"{p}: frame is {a.shape[1]}x{a.shape[0]} px; camera "
                                              f"{im.camera_id!r} expects {W}x{H}"))
                continue
            keep.append(im)
        self.images = keep

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


_WORKER_SURVEYS: dict[tuple, SurveyFrames] = {}


def open_survey(path: str, skip: tuple[str, ...] = (), dji_sdk: str | None = None) -> SurveyFrames:
    """The :class:`SurveyFrames` of ``path`` without the frames ``skip`` (the ones the run's checked instance skipped;
    not checked again), read through ``dji_sdk`` when given, kept for the next task of the same worker process (one
    survey at a time)."""
    key = (path, tuple(skip), dji_sdk or "")
    if key not in _WORKER_SURVEYS:
        _WORKER_SURVEYS.clear()
        _WORKER_SURVEYS[key] = SurveyFrames(path, dji_sdk=dji_sdk, need=1, check=False, skip=tuple(skip))
    return _WORKER_SURVEYS[key]
