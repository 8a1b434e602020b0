"""``report.html`` of ``survey``: moved to :mod:`thermogrammetry.pipeline.survey.report` (re-exported here)."""

from .survey.report import _axis_table, _f, _mapper_auto_text, _png, write_survey_report  # noqa: F401

__all__ = ["write_survey_report"]
