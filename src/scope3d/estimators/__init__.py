"""Estimation from correspondences: bundle adjustment with bounds (:mod:`.bundle`), triangulation
(:mod:`.triangulation`), relative poses and pose averaging (:mod:`.averaging`), ICP (:mod:`.icp`).
Absolute pose (PnP) lands here too.
"""
