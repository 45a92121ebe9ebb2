"""Stage 4 (issue 5, not built yet): metrics, baselines, tables and error against run time."""
