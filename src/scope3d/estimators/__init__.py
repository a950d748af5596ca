"""Estimation from correspondences: bundle adjustment with bounds (:mod:`.bundle`), triangulation
(:mod:`.triangulation`), relative poses and pose averaging (:mod:`.averaging`), start poses inside a cavity
(:mod:`.cavity_start`), ICP (:mod:`.icp`).
Absolute pose (PnP) lands here too.
"""
