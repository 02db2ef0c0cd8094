"""The SMLN browser viewer (viser): live rollouts, inspection overlays, side-by-side ablations, metrics, exports.

Modules, one job each: :mod:`app.sources` (outfits, clips, checkpoints, scenario loading, frame sources),
:mod:`app.rollout_worker` (background computation into capped frame caches), :mod:`app.extras` (saved rollouts
shown as read-only variants), :mod:`app.scene` (meshes and overlays), :mod:`app.controls` (GUI), :mod:`app.plots`
(metric table and uPlot curves), :mod:`app.uploads` (validated uploads), :mod:`app.server`
(:class:`~app.server.ViewerApp`, wiring and playback).
"""
