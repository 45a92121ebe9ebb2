"""Stage 4: evaluation — methods, metrics, tables, error against run time, stability.

    python -m pipeline eval [--spp 4 ...] [--scene a.xml ...]    (make eval)
    python -m pipeline stability                                  (make stability)

- ``evaluate.methods``: the denoisers behind one interface (noisy, OIDN, oidn_ft, Isik, AFGSA,
  ours and its variants), each loaded lazily, or not available with the reason.
- ``evaluate.harness``: one method on one frame: input repair, timing, output checks.
- ``evaluate.scoring``: the metric columns, over ``pipeline.metrics``.
- ``evaluate.stats``: confidence intervals: Student-t for means, paired bootstrap for
  differences, which lead is significant.
- ``evaluate.compare``: the statistics of one table from its per-frame scores (intervals,
  differences to the reference rows, leads).
- ``evaluate.headline``: the paragraph on top of ``eval.md``, generated from the leads.
- ``evaluate.timing``: the render-time model, equal-time spp, the spp a method is worth.
- ``evaluate.montecarlo``: plain MC as a method: convergence per frame, equal-time images.
- ``evaluate.uncertainty``: how well a denoiser's own per-pixel spread (``ours_kN``) predicts its
  error: rank correlation and calibration.
- ``evaluate.run``: the evaluation loop (``make eval``).
- ``evaluate.sequence``: every scene along its camera move: frames in order, the temporal filter
  baseline (``oidn_prefilter_temporal``), per-frame metrics and temporal instability.
- ``evaluate.sequence_report``: the sequence page (``sequence.md``): tables with frame 1 apart,
  per-frame curves, an animated strip.
- ``evaluate.report``: tables (Markdown, CSV, JSON), the error-vs-time plot, the crop grids.
- ``evaluate.stability``: every method on synthetic inputs that break denoisers (``make stability``).

See docs/evaluation.md.
"""
