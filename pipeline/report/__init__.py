"""Report stage: results -> what people read: the console tables
(``summary``), the frequency-response figure (``plot``) and the diagnosis
report with its figures (``diagnosis``; matplotlib loads only there)."""

from __future__ import annotations

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
