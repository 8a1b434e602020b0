"""Test helper: the synthetic scenes that several tests render and survey, built once per test run
(:mod:`_cache`, the ``scene_cache`` fixture of ``conftest.py``).

Each entry is keyed by the scene's whole configuration (``dataclasses.asdict``, defaults included) and, for a
survey, by its command-line arguments: a test that asks for the ring of seed 3 gets exactly the frames, user files
and survey output it would have made itself -- the builders are the calls the tests made before.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

from _cache import SceneCache, copy_entry


def _params(config) -> dict:
    return dataclasses.asdict(config)


# ------------------------------------------------------------------------------------ building rings
def building_ring_input(cache: SceneCache, config) -> Path:
    """A folder with what ``survey`` is given for the ring of ``config`` (a ``BuildingConfig``): ``frames/``
    (``write_building_survey``, with its true ``cameras.json``, ``mesh.obj`` and ``truth/``), ``gnss.csv`` and
    ``camera.json`` (``write_building_user_files`` with its defaults). Read-only."""

    def build(folder):
        from thermogrammetry.pipeline.project import FolderProject
        from thermogrammetry.synthetic.building import make_building, write_building_survey, write_building_user_files

        sc = make_building(config)
        project = FolderProject(folder)
        write_building_survey(project, sc)
        write_building_user_files(project, sc)

    return cache.folder("building-ring-input", _params(config), build)[0]


def tie_cache(cache: SceneCache) -> list:
    """``["--cache", <the run's tie-point cache>]``: the surveys of a test run share one cache of features and
    verified matches (``survey --cache``), so the surveys of the same frames detect and match them once; a survey
    that reads the cache gives the same outputs as one that computes (tests/test_survey_cache.py)."""
    return ["--cache", str(cache.root / "tie-cache")]


def building_ring_survey(cache: SceneCache, config, extra=(), *, copy_to: Path | None = None) -> tuple[Path, Path, int]:
    """``survey`` on the ring of ``config`` as the tests run it (``--input-unit K``, the ring's camera file and GNSS,
    ``--workers 0``, then ``extra``): ``(input folder, output folder, exit code)``.

    The output folder is the cache's (read-only) unless ``copy_to`` names where the test wants its own copy."""

    def build(folder):
        from thermogrammetry.cli.main import main

        inp = building_ring_input(cache, config)
        return main(["survey", str(inp / "frames"), "-o", str(folder / "out"), "--input-unit", "K", "--camera",
                     str(inp / "camera.json"), "--gnss", str(inp / "gnss.csv"), "--workers", "0", *extra, *tie_cache(cache)])

    folder, code = cache.folder("building-ring-survey", {"config": _params(config), "extra": list(extra)}, build)
    out = folder / "out"
    if copy_to is not None:
        out = copy_entry(out, copy_to)
    return building_ring_input(cache, config), out, code


# ------------------------------------------------------------------------------------ low-texture walk
def lowtexture_walk_folder(cache: SceneCache, scene) -> Path:
    """``write_lowtexture_facade(FolderProject(folder), scene)`` once per configuration (``frames/``, ``truth/``).
    Read-only."""

    def build(folder):
        from thermogrammetry.pipeline import FolderProject
        from thermogrammetry.synthetic.lowtexture_facade import write_lowtexture_facade

        write_lowtexture_facade(FolderProject(folder), scene)

    return cache.folder("lowtexture-walk", _params(scene.config), build)[0]


def building_images(cache: SceneCache, scene, stations=None, *, sensor: bool = False) -> list:
    """``render_building_thermal(scene, k, sensor=sensor)["image_k"]`` for the stations ``stations`` (default:
    all), each rendered once per test run for the scene's configuration (bit-identical: the renderer's noise is
    seeded by the configuration and the station)."""
    from thermogrammetry.synthetic.building import render_building_thermal

    params = _params(scene.config)
    ks = range(len(scene.stations)) if stations is None else stations
    return [cache.value("building-image", {"config": params, "station": int(k), "sensor": bool(sensor)},
                        lambda k=k: render_building_thermal(scene, k, sensor=sensor)["image_k"]) for k in ks]


# ------------------------------------------------------------------------------------ the UAV block of test_survey
def uav_block(cache: SceneCache) -> dict:
    """``tests/test_survey.py``'s UAV block (``uav_thermal_config(seed=0)``, the user's files with 0.3 px marker
    noise, bad inputs mixed in) and ``survey`` on it with GNSS, GCPs and check points, once per test run:
    ``{"scene", "root", "out", "code", "far", "dropped"}`` (``root`` holds ``survey/images`` and ``survey/user``;
    read-only)."""

    def build(folder):
        import shutil

        import numpy as np

        from thermogrammetry.cli.main import main
        from thermogrammetry.io.tiff import encode_temperature_tiff
        from thermogrammetry.pipeline.project import FolderProject
        from thermogrammetry.synthetic.survey import make_survey, render_frame, write_survey
        from thermogrammetry.synthetic.survey_files import uav_thermal_config, write_user_files

        scene = make_survey(uav_thermal_config(seed=0))
        proj = FolderProject(folder)
        write_survey(proj, scene, prefix="survey", threads=2)
        write_user_files(proj, scene, prefix="survey", marker_sigma_px=0.3, seed=0)
        images = folder / "survey" / "images"
        user = folder / "survey" / "user"
        # --- bad inputs mixed into the block ---------------------------------------------------------------------
        # a frame of another flight (another terrain), a truncated file
        other = make_survey(uav_thermal_config(seed=7))
        data, _ = encode_temperature_tiff(render_frame(other, 3)["image_k"])
        (images / "ZZ_other_flight.tif").write_bytes(data)
        good = (images / "T0005.tif").read_bytes()
        (images / "T0005_truncated.tif").write_bytes(good[: len(good) // 3])
        # a side file kept next to the frames (not a temperature matrix: skipped with a note, not a failed frame)
        shutil.copy(user / "gcps.csv", images / "gcps.csv")
        # two frames without GNSS
        lines = (user / "gnss.csv").read_text().splitlines()
        dropped = {"T0010", "T0030"}
        (user / "gnss.csv").write_text("\n".join(ln for ln in lines if ln.split(",")[0] not in dropped) + "\n")
        # a GCP "measured" in a frame where it is not visible (wrong identification)
        gcp1 = scene.gcps["GCP01"]
        far = max(scene.frames, key=lambda f: np.linalg.norm(f.pose.center[:2] - gcp1[:2]))
        with open(user / "gcp_measurements.csv", "a") as fh:
            fh.write(f"{far.name},GCP01,160.0,128.0\n")
        code = main(["survey", str(images), "-o", str(folder / "out"), "--workers", "0", "--gnss", str(user / "gnss.csv"),
                     "--crs", f"EPSG:{scene.terrain.epsg}", "--gcps", str(user / "gcps.csv"),
                     "--gcp-measurements", str(user / "gcp_measurements.csv"),
                     "--checkpoints", str(user / "checkpoints.csv"),
                     "--check-measurements", str(user / "check_measurements.csv"), *tie_cache(cache)])
        return {"scene": scene, "code": code, "far": far.name, "dropped": dropped}

    folder, value = cache.folder("uav-block-seed0", {"version": 1}, build)
    return {**value, "root": folder, "out": folder / "out"}


def survey_variant(cache: SceneCache, name: str, params, build) -> tuple[int, Path]:
    """``(exit code, OUT)`` of a survey run once per test run by ``build(folder) -> exit code`` (its OUT is
    ``folder / "out"``; read-only)."""
    folder, code = cache.folder(name, params, build)
    return code, folder / "out"
