"""Stage 1: scene randomizer, split-buffer Mitsuba integrator and the frame renderer."""
