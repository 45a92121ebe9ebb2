"""Stage 2 (issue 3, not built yet): Isik-style affinity network that turns GT1/GT2 into GT_clean."""
