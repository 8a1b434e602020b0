"""``thermogrammetry demo``: synthetic scenes with exact truth, every workflow run end to end, a report.

The demo is a list of **sections**. Each section makes (or reuses) a synthetic scene, runs a workflow
through the same library code paths as the real verb (the calibration workflow functions, the
close-range pipeline steps, the geometry kernels, the radiometry forward model ...) and returns
**rows**: what was achieved against the truth, each with a stated bound. :func:`demo_steps` turns the
sections into pipeline :class:`~thermogrammetry.pipeline.Step`\\ s; :func:`run_demo` runs them over a
project store, writes ``demo/<section>.json`` per section, ``reports/<section>.json`` (the step
report), ``demo/rows.json`` and ``report.html``; the CLI exits non-zero when any row misses its bound
or any section fails.

Adding a workflow to the demo
-----------------------------
Write a function ``run(project, options) -> list[DemoRow]`` (it may write files through ``project``
under its own prefix, e.g. ``"mysection/"``; keep it well under a minute) and register it::

    from thermogrammetry.pipeline.demo import DemoRow, DemoSection, register_section

    def _my_section(project, options):
        ...                                  # make a scene, run the workflow's library entry point
        return [DemoRow("my workflow", "point error (max)", achieved_mm, 5.0, "mm", note="...")]

    register_section(DemoSection("mine", "My workflow", _my_section))

Rows compare ``value`` with ``bound``: ``kind="max"`` passes when value ≤ bound (errors),
``kind="min"`` when value ≥ bound (counts, rates), ``kind="info"`` never fails (context numbers).
A section that raises is reported as a failed row. Sections are run in registration order;
``DemoOptions.sections`` selects a subset by name. Sections registered from other modules must be
imported before :func:`run_demo` (add the module to :data:`SECTION_MODULES`).

The built-in sections: ``render`` (geometric and radiometric exactness of the renderer),
``calibration-target`` (rendered circle-grid images → detection → self-calibration),
``calibration-testfield`` (the 3D test field of Yastikli & Guler 2013 → self-calibration), ``closerange``
(the network of Sawicki, Stein & Więcek → the close-range pipeline), ``survey`` (rendered UAV survey → resection / triangulation of
the ground-control markers, per-pixel temperature recovery), ``survey-bundle`` (the adjustment
engine on the survey's exact tie points + GNSS + GCPs, accuracy at check points), ``facade`` (facade mesh + rig → the
per-pixel correction over a mesh used by ``thermogrammetry correct --mesh``).

Modules
-------
This module runs the sections and re-exports the demo's names: :mod:`.demo_registry` (rows, sections,
options, the registry, :class:`PrefixedProject`), one module per group of sections (:mod:`.demo_render`,
:mod:`.demo_calibration`, :mod:`.demo_closerange`, :mod:`.demo_uav`, :mod:`.demo_facade`;
:mod:`.demo_survey` registers ``survey-sfm`` itself) and :mod:`.demo_report` (``report.html``).
"""

from __future__ import annotations

import importlib
import time
from typing import Callable

from ..errors import ConfigError
# the demo's names live in these modules; re-exported here (import them from thermogrammetry.pipeline.demo)
from .demo_calibration import (CALIB_C_BOUND_PCT, match_to_truth, section_calibration_target,  # noqa: F401
                               section_calibration_testfield)
from .demo_closerange import CLOSERANGE_THERMAL_CENTRE_BOUND_MM, section_closerange  # noqa: F401
from .demo_facade import section_facade
from .demo_registry import (DEMO_SECTIONS, SECTION_MODULES, DemoOptions, DemoResult, DemoRow, DemoSection,
                            PrefixedProject, register_section)
from .demo_render import section_render
from .demo_report import report_html, rows_json  # noqa: F401
from .demo_uav import (BUNDLE_CENTRE_BOUND_M, BUNDLE_CHECK_BOUND_GSD, RESECTION_CENTRE_BOUND_REL,  # noqa: F401
                       RESECTION_MIN_COVER, TRIANGULATION_BOUND_GSD, image_gsd_m, section_survey, section_survey_bundle)
from .project import ProjectStore
from .steps import Step, StepReport, run_steps

__all__ = [
    "DemoRow",
    "DemoSection",
    "DemoOptions",
    "DemoResult",
    "DEMO_SECTIONS",
    "SECTION_MODULES",
    "all_sections",
    "register_section",
    "demo_steps",
    "run_demo",
    "report_html",
    "PrefixedProject",
    "match_to_truth",
]


for _s in (
    DemoSection("render", "Renderer exactness", section_render),
    DemoSection("calibration-target", "Calibration from rendered circle-grid images", section_calibration_target),
    DemoSection("calibration-testfield", "Calibration on a 3D test field (Yastikli & Guler 2013)", section_calibration_testfield),
    DemoSection("closerange", "Close-range network and angle correction (Sawicki, Stein & Więcek)", section_closerange),
    DemoSection("survey", "UAV thermal survey, set-up of Khodaei et al. (starts from true correspondences)", section_survey),
    DemoSection("survey-bundle", "UAV survey bundle adjustment with GNSS, GCPs and check points (starts from true tie points)", section_survey_bundle),
    DemoSection("facade", "Facade mesh, thermal + RGB rig, correction over the mesh (Barazzetti et al. 2013)", section_facade),
):
    register_section(_s)


# ------------------------------------------------------------------------------------------ running

def all_sections() -> list[DemoSection]:
    """Every registered section, in run order (the built-in ones and those of :data:`SECTION_MODULES`)."""
    for mod in SECTION_MODULES:
        importlib.import_module(mod)
    return list(DEMO_SECTIONS)


def _selected(options: DemoOptions) -> list[DemoSection]:
    all_sections()
    if options.sections is None:
        return list(DEMO_SECTIONS)
    names = {s.name: s for s in DEMO_SECTIONS}
    unknown = [n for n in options.sections if n not in names]
    if unknown:
        raise ConfigError(f"unknown demo section(s) {unknown}; valid: {list(names)}")
    return [names[n] for n in options.sections]


def demo_steps(options: DemoOptions | None = None) -> list[Step]:
    """One pipeline step per selected section; each writes ``demo/<name>.json`` with its rows."""
    opt = options or DemoOptions()
    steps = []
    for sec in _selected(opt):
        def run(project, sec=sec):
            rows = sec.run(project, opt)
            data = [r.to_dict() for r in rows]
            project.write_json(f"demo/{sec.name}.json", {"section": sec.name, "title": sec.title, "rows": data})
            return {"rows": data, "passed": all(r["passed"] for r in data)}

        steps.append(Step(sec.name, run, sec.title))
    return steps


def run_demo(project: ProjectStore, options: DemoOptions | None = None, *, on_section: Callable | None = None) -> DemoResult:
    """Run every selected section (a failing section does not stop the others) and write the report."""
    opt = options or DemoOptions()
    t0 = time.perf_counter()
    rows: list[DemoRow] = []
    reports: list[StepReport] = []
    for step in demo_steps(opt):
        rep = run_steps(project, [step])[0]
        reports.append(rep)
        if rep.ok:
            got = [DemoRow(**{k: v for k, v in d.items() if k != "passed"}) for d in rep.summary["rows"]]
        else:
            got = [DemoRow(step.name, f"section failed: {rep.error}", float("nan"), 0.0, "")]
        rows.extend(got)
        if on_section is not None:
            on_section(rep, got)
    res = DemoResult(rows, reports, time.perf_counter() - t0)
    project.write_json("demo/rows.json", {"ok": res.ok, "seconds": res.seconds, "rows": [r.to_dict() for r in rows]})
    project.write_text("report.html", report_html(res))
    return res
