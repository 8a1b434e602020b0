"""The ``run`` verb's driver: a flight's images → one project folder with the survey, the DSM and cloud, the ortho.

Layout of PROJECT (each step folder is written by the verb's own driver, as one output set: complete or absent, a
user's own files in it kept)::

    PROJECT/survey/     the ``survey`` verb's outputs (cameras.json, survey.json, report.html, ...)
    PROJECT/dense/      the ``dense`` verb's outputs (dsm.tif, cloud.las, cloud.ply, dense.json)
    PROJECT/ortho/      the ``ortho`` verb's outputs on dense/dsm.tif (ortho.tif, ortho.qml, ortho.json, ...)
    PROJECT/report.html an index: each step's status (ran / skipped), time, key figures and links
    PROJECT/run.log     progress lines and the libraries' own messages, appended by every run
    PROJECT/run.json    per step: the hash of its inputs, its manifest's hash, time, key figures

A step's *input hash* covers what its outputs depend on: for the survey the input files (path, size and
modification time of every image; the bytes of the CSV, camera and rig files), the options (without ``workers`` /
``scheduler``, which do not change the outputs) and the software version; for ``dense`` and ``ortho`` the upstream
step's hash and the hash of its manifest (and of the survey's cameras.json). A step is *finished* when run.json
holds its hash and the hash of its manifest, and the manifest and the files it lists are in place: a killed run
resumes at the first unfinished step, a run with nothing changed skips every step and rewrites no file (run.log,
which every run appends to, aside). ``--rerun-from STEP`` runs STEP and the steps after it whatever their hashes.

The products: ``dsm`` and ``cloud`` are ``dense``'s, ``ortho`` needs ``dense``; ``mesh`` and ``texture`` are not
built by ``run`` yet (there is no ``mesh`` verb) and are refused.
"""

from __future__ import annotations

import json
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Sequence

from .. import __version__
from .._atomic import check_output_folder, write_atomic_text
from ..errors import ConfigError, ThermogrammetryError
from ..reporting import driver_call
from .runlog import RunLog, digest, file_digest, options_digest, stat_digest

__all__ = ["STEPS", "PRODUCTS", "parse_products", "check_rerun_from", "run_project", "ProjectRun", "StepResult"]

#: the steps of a run, in order
STEPS = ("survey", "dense", "ortho")
#: the products ``--products`` accepts and the last step each needs
PRODUCTS = {"ortho": "ortho", "dsm": "dense", "cloud": "dense"}
#: products named in the contract that ``run`` does not build yet, and why
NOT_BUILT = {
    "mesh": "run does not build meshes yet (there is no mesh verb); leave mesh out of --products",
    "texture": "run does not build textured meshes yet (it needs a mesh, and there is no mesh verb); leave texture out "
               "of --products, or texture a mesh of your own with 'thermogrammetry texture PROJECT/survey --mesh MESH'",
}
RUN_FORMAT = "thermogrammetry-run"
#: a step that reports no progress for this long gets a "still running" line (s)
HEARTBEAT_S = 30.0


def parse_products(text: str | Sequence[str]) -> tuple[str, ...]:
    """``"ortho,dsm,cloud"`` → ``("ortho", "dsm", "cloud")`` (order of :data:`PRODUCTS`); :class:`ConfigError` for an
    unknown product or one not built yet (``mesh``, ``texture``)."""
    items = [p.strip().lower() for p in (text.split(",") if isinstance(text, str) else text) if p.strip()]
    if not items:
        raise ConfigError(f"--products {text!r}: expected a comma-separated list of {', '.join(PRODUCTS)}")
    for p in items:
        if p in NOT_BUILT:
            raise ConfigError(f"--products {p}: {NOT_BUILT[p]}")
        if p not in PRODUCTS:
            raise ConfigError(f"--products {p!r}: unknown product; expected a comma-separated list of {', '.join(PRODUCTS)}")
    return tuple(p for p in PRODUCTS if p in items)


def steps_for(products: Sequence[str]) -> list[str]:
    """The steps that build ``products`` (always the survey first)."""
    last = max(STEPS.index(PRODUCTS[p]) for p in products) if products else 0
    return list(STEPS[: last + 1])


def check_rerun_from(step: str | None, products: Sequence[str] = tuple(PRODUCTS)) -> str | None:
    """``--rerun-from`` checked against the steps of ``products``; :class:`ConfigError` when unknown or not run."""
    if step is None:
        return None
    s = step.strip().lower()
    if s not in STEPS:
        raise ConfigError(f"--rerun-from {step!r}: unknown step; expected one of {', '.join(STEPS)}")
    if s not in steps_for(products):
        raise ConfigError(f"--rerun-from {s}: not a step of --products {','.join(products)} "
                          f"(its steps: {', '.join(steps_for(products))})")
    return s


@dataclass
class StepResult:
    """One step of a run: ``status`` ``"ran"``, ``"skipped"`` (its inputs unchanged) or ``"failed"``."""

    name: str
    status: str
    seconds: float = 0.0
    summary: dict = field(default_factory=dict)
    message: str = ""


@dataclass
class ProjectRun:
    """What :func:`run_project` did: the steps in order, the failed one (None when all ran or were skipped) and
    ``bad_input`` when the failure is the user's input (the survey's ``inputs`` step)."""

    project: Path
    steps: list
    failed: StepResult | None = None
    bad_input: bool = False

    @property
    def ok(self) -> bool:
        return self.failed is None


class _Meter:
    """Progress of one step: the callback of the CLI, and a line in run.log every 10 % of a stage (with the elapsed
    time of the step)."""

    def __init__(self, log: RunLog, step: str, progress: Callable | None):
        self.log, self.step, self.progress = log, step, progress
        self.t0 = time.perf_counter()
        self.last: dict = {}
        self.last_stage = ""
        self.last_report = self.t0

    def heartbeat(self, every_s: float = HEARTBEAT_S):
        """A thread that writes "still running" to run.log and the terminal every ``every_s`` seconds without a
        progress report (a stage that reports none, e.g. the survey's final adjustment); ``stop()`` ends it."""
        import threading

        stop = threading.Event()
        self.last_report = time.perf_counter()

        def beat():
            while not stop.wait(every_s / 4):
                now = time.perf_counter()
                if now - self.last_report >= every_s:
                    self.last_report = now
                    after = f"; last: {self.last_stage}" if self.last_stage else ""
                    self.log.line(f"{self.step}: still running ({now - self.t0:.0f} s{after})")

        t = threading.Thread(target=beat, name=f"run-{self.step}-heartbeat", daemon=True)
        t.start()
        return stop

    def __call__(self, stage: str, done: int, total: int) -> None:
        self.last_report = time.perf_counter()
        self.last_stage = f"{stage} {done}/{total}"
        if self.progress is not None:
            self.progress(self.step, stage, done, total)
        dec = int(10 * done / max(total, 1))
        if self.last.get(stage) != dec or done == total and self.last.get(stage, -1) != 10:
            self.last[stage] = dec
            self.log.write(f"{self.step} {stage}: {done}/{total} ({time.perf_counter() - self.t0:.1f} s)")


def _survey_hash(inp, opt) -> str:
    from ..io.dji_sdk import sdk_path
    from .survey.inputs import expand_inputs

    thermal, _ = expand_inputs(inp.images, kind="thermal")
    rgb, _ = expand_inputs(inp.rgb, kind="rgb") if inp.rgb else ([], [])
    rig = None
    if inp.rig is not None:
        src = getattr(inp.rig, "source", None)
        rig = file_digest(src) if src and Path(src).is_file() else repr(inp.rig)
    gnss = file_digest(opt.gnss) if str(opt.gnss).lower() not in ("auto", "none") else opt.gnss
    sdk = sdk_path(getattr(opt, "dji_sdk", None))
    return digest({
        "version": __version__,
        "images": [stat_digest(p) for p in thermal], "rgb": [stat_digest(p) for p in rgb],
        "files": {k: file_digest(getattr(inp, k)) if getattr(inp, k) else None
                  for k in ("gcps", "gcp_measurements", "checkpoints", "check_measurements")},
        "camera": None if inp.camera is None else inp.camera.to_dict(), "rig": rig, "gnss": gnss,
        "dji_sdk": None if sdk is None else stat_digest(sdk), "options": options_digest(opt),
    })


def _manifest(folder: Path, verb: str) -> Path:
    return folder / f"{verb}-manifest.json"


def _finished(rec: dict | None, h: str, folder: Path, verb: str) -> bool:
    """The step's record matches ``h`` and its outputs are in place (manifest unchanged, every file it lists there)."""
    if not rec or rec.get("hash") != h:
        return False
    man = _manifest(folder, verb)
    if file_digest(man) != rec.get("manifest_sha256"):
        return False
    try:
        names = json.loads(man.read_text()).get("files", [])
    except (OSError, ValueError):
        return False
    return all((folder / n).is_file() for n in names)


def _load_record(path: Path) -> dict:
    try:
        d = json.loads(path.read_text())
    except (OSError, ValueError):
        return {}
    return d if isinstance(d, dict) and d.get("format") == RUN_FORMAT else {}


def _write_if_changed(path: Path, text: str) -> bool:
    try:
        if path.read_text(encoding="utf-8") == text:
            return False
    except (OSError, UnicodeError):
        pass
    write_atomic_text(path, text)
    return True


def _survey_summary(s: dict) -> dict:
    cp = s.get("checkpoints") or {}
    return {"images_oriented": s.get("images_oriented"), "images_total": s.get("images_total"),
            "blocks": s.get("components"), "reprojection_rms_px": s.get("reprojection_rms_px"), "crs": s.get("crs"),
            "checkpoints": {k: cp.get(k) for k in ("n", "rmse_x", "rmse_y", "rmse_z")} if cp.get("n") else None}


def _dense_summary(r: dict) -> dict:
    return {"points": r["points"], "gsd_m": r["gsd_m"], "completeness": r["completeness"], "unit": r["unit"],
            "dsm_cells": [r["dsm"]["width"], r["dsm"]["height"]]}


def _ortho_summary(r: dict) -> dict:
    box = max(1, int(r["width"]) * int(r["height"]))
    return {"cells": r["cells"], "size": [r["width"], r["height"]], "gsd_m": r["gsd_m"], "unit": r["unit"],
            "coverage": round(r["cells"] / box, 4), "images_used": r["images_used"],
            "footprint_coverage": (r.get("footprint") or {}).get("covered")}


def run_project(project, inp, opt, *, products: Sequence[str] = tuple(PRODUCTS), rerun_from: str | None = None,
                log: RunLog | None = None, progress: Callable | None = None) -> ProjectRun:
    """Run the steps that build ``products`` into ``project`` (see the module docstring), skipping those whose inputs
    are unchanged.

    Parameters
    ----------
    project : path of PROJECT (created; a user's files in it are kept)
    inp, opt : the survey's :class:`~thermogrammetry.pipeline.survey.SurveyInput` and ``SurveyOptions``
        (``opt.workers`` / ``opt.scheduler`` also spread dense and ortho)
    products : subset of :data:`PRODUCTS`
    rerun_from : a step of :data:`STEPS` run with the steps after it whatever their hashes, or None
    log : the :class:`RunLog` of ``project/run.log`` (opened here when None)
    progress : ``progress(step, stage, done, total)`` or None

    Returns
    -------
    ProjectRun; a failed step stops the run (the steps before it stay finished).
    """
    from .survey.workflow import check_survey_output

    project = check_output_folder(project, "project folder")
    check_survey_output(project, inp, "project folder", opt)  # before run.log is written into it
    products = parse_products(list(products))
    rerun_from = check_rerun_from(rerun_from, products)
    project.mkdir(parents=True, exist_ok=True)
    own_log = log is None
    call = driver_call(run_project, locals())  # the reports' command line when called from Python
    log = log or RunLog(project / "run.log")
    try:
        with call:
            return _run(project, inp, opt, products, rerun_from, log, progress)
    finally:
        if own_log:
            log.close()


def _run(project: Path, inp, opt, products, rerun_from, log: RunLog, progress) -> ProjectRun:
    from .dense import run_dense
    from .ortho import run_ortho
    from .survey import survey_to_folder

    steps = steps_for(products)
    forced = set(STEPS[STEPS.index(rerun_from):]) if rerun_from else set()
    record_path = project / "run.json"
    old = _load_record(record_path)
    recs: dict = dict(old.get("steps", {}))
    log.write(f"run {project} (thermogrammetry {__version__}): products {','.join(products)}, steps {', '.join(steps)}"
              + (f", rerun from {rerun_from}" if rerun_from else ""))
    results: list[StepResult] = []
    out = ProjectRun(project, results)
    workers, scheduler = opt.workers, opt.scheduler
    for name in steps:
        folder = project / name
        if name == "survey":
            h = _survey_hash(inp, opt)
        else:
            up = "survey" if name == "dense" else "dense"
            h = digest({"version": __version__, "upstream": recs[up]["hash"], "upstream_manifest": recs[up]["manifest_sha256"],
                        "cameras": file_digest(project / "survey" / "cameras.json"), "options": {}})
        if name not in forced and _finished(recs.get(name), h, folder, name):
            r = recs[name]
            results.append(StepResult(name, "skipped", r.get("seconds", 0.0), r.get("summary", {})))
            log.line(f"{name}: skipped (inputs, options and upstream unchanged since {r.get('finished_utc', '?')})")
            continue
        meter = _Meter(log, name, progress)
        log.line(f"{name}: running")
        t0 = time.perf_counter()
        beating = meter.heartbeat()
        try:
            if name == "survey":
                sr = survey_to_folder(folder, inp, opt, progress=lambda step, k, n: meter(step, k, n))
                if sr.failed is not None:
                    first = sr.failed.error.strip().splitlines()[-1] if sr.failed.error else "failed"
                    msg = first.split(": ", 1)[-1] if first.startswith(("DataFileError", "UnsupportedFormatError")) else first
                    res = StepResult(name, "failed", time.perf_counter() - t0,
                                     message=f"survey step {sr.failed.name} failed: {msg}")
                    out.failed, out.bad_input = res, sr.failed.name == "inputs"
                    results.append(res)
                    break
                summary = _survey_summary(sr.survey)
            elif name == "dense":
                rep = run_dense(project / "survey", folder, workers=workers, scheduler=scheduler,
                                on_image=lambda k, n: meter("reference images", k, n))
                summary = _dense_summary(rep)
            else:
                rep = run_ortho(project / "survey", project / "dense" / "dsm.tif", folder, workers=workers,
                                scheduler=scheduler, on_tile=lambda k, n: meter("tiles", k, n))
                summary = _ortho_summary(rep)
        except ThermogrammetryError as exc:
            res = StepResult(name, "failed", time.perf_counter() - t0, message=f"{name} failed: {exc}")
            out.failed = res
            results.append(res)
            break
        finally:
            beating.set()
        dt = time.perf_counter() - t0
        recs[name] = {"hash": h, "manifest": f"{name}/{name}-manifest.json",
                      "manifest_sha256": file_digest(_manifest(folder, name)), "seconds": round(dt, 2),
                      "finished_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()), "summary": summary}
        # the step is finished only now: its outputs are published and its hash is recorded
        _write_if_changed(record_path, _record_text(recs, products))
        results.append(StepResult(name, "ran", dt, summary))
        log.line(f"{name}: ran in {dt:.1f} s: {_figures(name, summary)}")
        if name == "survey" and not summary.get("images_oriented"):
            res = StepResult("dense", "failed", message="the survey oriented no image: dense and ortho need an oriented "
                             f"block (see {folder / 'report.html'})")
            out.failed = res
            results.append(res)
            break
    if not out.bad_input and (any(r.status != "skipped" for r in results) or not (project / "report.html").is_file()):
        from .run_report import run_header, write_run_report

        _write_if_changed(record_path, _record_text(recs, products))
        write_run_report(project, results, recs, products, run_header(project, results, recs, inp.images))
    return out


def _record_text(recs: dict, products) -> str:
    doc = {"format": RUN_FORMAT, "version": 1, "software": f"thermogrammetry {__version__}", "products": list(products),
           "steps": {k: recs[k] for k in STEPS if k in recs}}
    return json.dumps(doc, indent=1, default=float) + "\n"


def _figures(name: str, s: dict) -> str:
    """The key figures of a step, one line."""
    if name == "survey":
        t = f"{s.get('images_oriented')}/{s.get('images_total')} images oriented"
        if s.get("reprojection_rms_px") is not None:
            t += f", reprojection RMS {s['reprojection_rms_px']:.3f} px"
        cp = s.get("checkpoints")
        if cp:
            t += f", check points n={cp['n']} RMSE X {cp['rmse_x']:.3f} Y {cp['rmse_y']:.3f} Z {cp['rmse_z']:.3f} m"
        return t
    if name == "dense":
        return (f"{s['points']} points, DSM {s['dsm_cells'][0]}×{s['dsm_cells'][1]} cells at {s['gsd_m']} m, "
                f"completeness {100 * s['completeness']:.1f} %")
    fp = s.get("footprint_coverage")
    return (f"ortho {s['size'][0]}×{s['size'][1]} cells at {s['gsd_m']} m in {s['unit']}, "
            + (f"{100 * fp:.1f} % of the frames' footprint covered, " if fp is not None else "")
            + f"coverage of its box {100 * s['coverage']:.1f} %, {s['images_used']} images used")
