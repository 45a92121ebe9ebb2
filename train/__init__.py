"""Stage 3 (issue 4, not built yet): frozen pixel-space diffusion base + trainable Control Module."""
