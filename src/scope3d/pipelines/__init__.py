"""Pipelines: short scripts of stage calls, each stage a ``run``-style function (options, inputs, out_dir).

* :mod:`scope3d.pipelines.surgical_map` — the multimodal metric map of a surgical field from a
  robot-held scope of known-but-inaccurate poses (reference chapters 3, 4 and 6).
"""
