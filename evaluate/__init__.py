"""Stage 4: evaluation — methods, metrics, tables, error against run time, stability.

    python -m pipeline eval [--spp 4 ...] [--scene a.xml ...]    (make eval)
    python -m pipeline stability                                  (make stability)

Modules: ``methods`` (the denoisers behind one interface), ``harness`` (input repair, timing,
output checks), ``scoring`` (metric columns over ``pipeline.metrics``), ``timing`` (render-time
model, equal-time spp, spp equivalent), ``montecarlo`` (MC convergence and equal-time images),
``run`` (the evaluation loop), ``report`` (tables, plots, crops), ``stability`` (edge cases).
See docs/evaluation.md.
"""
