"""Estimation from correspondences: bundle adjustment with bounds (:mod:`.bundle`), triangulation
(:mod:`.triangulation`), relative poses and pose averaging (:mod:`.averaging`), start poses inside a cavity
(:mod:`.cavity_start`), a similarity from measurements (:mod:`.gauge`), ICP (:mod:`.icp`), absolute pose:
PnP and bounded pose-only refinement (:mod:`.absolute_pose`, compiled :mod:`.pose_kernels`), a pose filter
and the fusion of pose sources (:mod:`.kalman`), a marker plate's rigid pose (:mod:`.marker_plate`), a
camera/robot clock offset from measured and adjusted camera centres (:mod:`.clock_offset`).
"""
