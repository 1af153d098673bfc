"""Report stage: tables, figures and the report for people."""
