"""The survey as a list of steps over the store (:func:`survey_steps`), the run (:func:`run_survey`) and the
verb's driver (:func:`survey_to_folder`: the run in a staging folder, published as one output set)."""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

from ...store import ProjectStore
from .features import step_features
from .georef import step_georef
from .inputs import step_inputs
from .lowtexture import step_orient_low_texture
from .matching import step_matching
from .options import SurveyInput, SurveyOptions
from .store import SurveyStore
from .tasks import _TASK_STEPS, _local_cluster, _release_task_state


def _survey_camera(inp: SurveyInput):
    """The thermal camera held fixed: ``--camera``, else the rig file's thermal camera, else None."""
    cam = inp.camera
    if cam is None and inp.rig is not None and inp.rig.thermal_camera is not None:
        cam = inp.rig.thermal_camera  # the rig file's thermal camera, held fixed like --camera
    return cam


def _retry_low_texture(project: ProjectStore, opt: SurveyOptions, reports) -> bool:
    """True when ``georef`` ran and oriented nothing although ``orient`` gave blocks, with ``--low-texture auto``
    and the fallback not yet run (:func:`step_orient_low_texture` ``primary_rejected``)."""
    if opt.low_texture != "auto" or not reports or reports[-1].name != "georef" or not reports[-1].ok:
        return False
    if reports[-1].summary.get("images_oriented", 1) != 0 or not SurveyStore(project).has_low_texture():
        return False
    orient = next((r for r in reports if r.name == "orient"), None)
    if orient is None or not orient.summary.get("oriented"):
        return False
    return not SurveyStore(project).load_low_texture().get("ran", True)


def _restart_from_self_calibration(project: ProjectStore, plain, reports, on_step) -> list:
    """The orientation and the final adjustment again, from the self-calibrated thermal camera, when its start was
    the camera table's field of view and that field of view says another focal length through the distortion the
    block found (:func:`~.camera_start.restart_camera`): the start's ``camera_guess.start`` in ``work/inputs.json``,
    steps ``orient_restart`` and ``georef_restart``; the survey then reports the second orientation."""
    from ...store import Step, run_steps
    from .camera_start import restart_camera

    if not reports or not all(r.ok for r in reports) or not SurveyStore(project).has_survey():
        return []
    inputs = SurveyStore(project).load_inputs()
    thermal = [im for im in inputs["images"] if im.get("sensor", "thermal") == "thermal"]
    if len({(im["width"], im["height"]) for im in thermal}) != 1:
        return []  # the start is set per thermal frame: only a block of one thermal camera is oriented again
    st = restart_camera(inputs, SurveyStore(project).load_survey()).get("thermal")
    if st is None:
        return []
    for im in thermal:
        im["camera_guess"]["start"] = st
    SurveyStore(project).save_inputs(inputs)
    by = {s.name: s for s in plain}
    out = run_steps(project, [Step(f"{name}_restart", by[name].run, by[name].description) for name in ("orient", "georef")],
                    on_step=on_step)
    if SurveyStore(project).has_survey():
        s = SurveyStore(project).load_survey()
        s.setdefault("notes", []).append(
            f"thermal camera oriented again from its self-calibration: the camera table's field of view through the "
            f"self-calibrated distortion gives {st['fx']:.1f} px (k1 {st['k1']:.3f}, k2 {st['k2']:.3f}) as the start")
        SurveyStore(project).save_survey(s)
    return out


def survey_steps(inp: SurveyInput, opt: SurveyOptions, progress: Callable | None = None):
    """The survey as a list of :class:`~thermogrammetry.pipeline.steps.Step`."""
    from ...store import Step

    cam = _survey_camera(inp)

    def prog(name):
        return (lambda k, n: progress(name, k, n)) if progress else None

    return [
        Step("inputs", lambda p: step_inputs(p, inp, opt, prog("inputs")), "decode inputs to frames/"),
        Step("features", lambda p: step_features(p, opt, prog("features")), "tie-point features per image"),
        Step("matching", lambda p: step_matching(p, opt, cam, prog("matching"), rig=inp.rig), "pairs, matching, geometric verification"),
        Step("orient", lambda p: step_orient_low_texture(p, opt, cam, prog("orient"), rgb_camera=getattr(inp.rig, "rgb_camera", None),
                                                         rig=inp.rig),
             "tracks and incremental orientation"),
        Step("georef", lambda p: step_georef(p, inp, opt, cam, prog("georef")), "georeferencing, final adjustment, exports"),
    ]


def run_survey(project: ProjectStore, inp: SurveyInput, opt: SurveyOptions | None = None, *, progress: Callable | None = None,
               on_step: Callable | None = None):
    """Run every step; writes ``report.html`` and the step reports. Returns the list of StepReport."""
    from ...store import run_steps
    from .report import survey_geometry, write_survey_report

    opt = opt or SurveyOptions()
    t0 = time.perf_counter()
    # the steps that run tasks share one local cluster; it is closed before the orientation, whose memory then
    # starts without the cluster's state and what the earlier steps left in the process (a later step that runs
    # tasks again, e.g. the low-texture fallback of ``orient``, starts a cluster of its own)
    plain = survey_steps(inp, opt, progress)
    n_tasks = next((k for k, s in enumerate(plain) if s.name not in _TASK_STEPS), len(plain))
    with _local_cluster(opt) as opt_run:
        reports = run_steps(project, survey_steps(inp, opt_run, progress)[:n_tasks], on_step=on_step)
    _release_task_state()
    if all(r.ok for r in reports) and n_tasks < len(plain):
        reports += run_steps(project, plain[n_tasks:], on_step=on_step)
    if _retry_low_texture(project, opt, reports):
        # the final adjustment rejected every block of the primary orientation: the low-texture fallback, then the
        # georeferencing again on its blocks (steps of their own, reported beside the first ones)
        from ...store import Step

        cam = _survey_camera(inp)
        retry = [Step("orient_low_texture", lambda p: step_orient_low_texture(
                     p, opt, cam, (lambda k, n: progress("orient", k, n)) if progress else None,
                     rgb_camera=getattr(inp.rig, "rgb_camera", None), rig=inp.rig, primary_rejected=True),
                      "low-texture fallback after the final adjustment rejected the primary blocks")]
        reports += run_steps(project, retry, on_step=on_step)
        if reports[-1].ok:  # (also when the fallback was not kept: survey.json then says why)
            reports += run_steps(project, [Step("georef_low_texture", plain[-1].run, plain[-1].description)], on_step=on_step)
    reports += _restart_from_self_calibration(project, plain, reports, on_step)
    if SurveyStore(project).has_survey():
        s = SurveyStore(project).load_survey()
        s["seconds"] = time.perf_counter() - t0
        s["steps"] = [{"name": r.name, "seconds": r.seconds, "status": r.status} for r in reports]
        s["inputs"] = _inputs_record(inp)
        s["footprints"] = survey_geometry(project)
        SurveyStore(project).save_survey(s)
        write_survey_report(project)
    return reports


def _inputs_record(inp: SurveyInput) -> dict:
    """survey.json's ``inputs``: the folders of the thermal and RGB images and the control files, as absolute paths."""
    from ...reporting import folders_of

    files = {k: str(Path(getattr(inp, k)).resolve()) for k in ("gcps", "gcp_measurements", "checkpoints", "check_measurements")
             if getattr(inp, k)}
    rig = getattr(inp.rig, "source", None) if inp.rig is not None else None
    return {"image_folders": folders_of(inp.images), "rgb_folders": folders_of(inp.rgb), **files,
            **({"rig": str(rig)} if rig else {})}


@dataclass
class SurveyRun:
    """What :func:`survey_to_folder` did: the step reports, the first failed step (None when every step ran; OUT is
    then unchanged) and ``survey.json`` of a published run."""

    reports: list
    failed: object | None = None
    survey: dict = field(default_factory=dict)


def check_survey_output(out, inp: SurveyInput, what: str = "-o", opt: SurveyOptions | None = None) -> None:
    """Refuse an output folder that is one of the survey's input folders (thermal or RGB), or lies inside or around
    one (:func:`~thermogrammetry._atomic.check_output_apart`); with ``opt``, a tie-point cache path that is a file
    (:func:`~.cache.check_cache_path`)."""
    from ..._atomic import check_output_apart
    from .cache import check_cache_path

    check_output_apart(out, [("input images' folder", p) for p in inp.images or []]
                       + [("RGB images' folder", p) for p in inp.rgb or []], what)
    if opt is not None:
        check_cache_path(opt.cache)


def survey_to_folder(out, inp: SurveyInput, opt: SurveyOptions | None = None, *, progress: Callable | None = None,
                     on_step: Callable | None = None) -> SurveyRun:
    """The ``survey`` verb: run every step in a staging folder beside ``out`` and publish it as one output set
    (:class:`~thermogrammetry._atomic.OutputSet`: OUT appears complete or not at all; files of the user's own in OUT
    are kept). A run whose steps all ran is published even when it oriented nothing (``survey.json`` says why); a
    failed step leaves OUT as it was. An OUT that is an input folder, or lies inside or around one, is refused first
    (:func:`check_survey_output`)."""
    from ..._atomic import OutputSet, sync_folder
    from ...reporting import driver_call
    from ...store import FolderProject

    check_survey_output(out, inp, opt=opt)
    with driver_call(survey_to_folder, locals()), OutputSet(out, "survey") as outputs:
        # files are flushed once before the staging folder is published, not one by one (several hundred)
        project = FolderProject(outputs.stage, durable=False)
        reports = run_survey(project, inp, opt, progress=progress, on_step=on_step)
        failed = [r for r in reports if not r.ok]
        if failed:
            return SurveyRun(reports, failed[0])
        s = SurveyStore(project).load_survey()
        sync_folder(outputs.stage)
        outputs.commit({"images_oriented": s["images_oriented"], "images_total": s["images_total"]})
    return SurveyRun(reports, survey=s)
