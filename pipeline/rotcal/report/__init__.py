"""Report stage: results -> what people read: the console tables
(``summary``), the frequency-response figure (``plot``) and the diagnosis
report with its figures (``diagnosis``; matplotlib loads only there); and
how a run's output directory is published whole (``publish``). The console
tables load at first use, so that the command line checks an output
directory (``publish``) before it loads the stages (scipy)."""

from __future__ import annotations

from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from rotcal.report.summary import (
        findings_table,
        matrix_table,
        pose_check_table,
        recommendation_line,
        run_summary,
        static_fit_summary,
        summary_table,
    )

__all__ = ["findings_table", "matrix_table", "pose_check_table", "recommendation_line", "run_summary",
           "static_fit_summary", "summary_table"]


def __getattr__(name: str) -> object:
    if name in __all__:
        from rotcal.report import summary

        return getattr(summary, name)
    raise AttributeError(f"module 'rotcal.report' has no attribute {name!r}")
