"""Structure from motion with known-but-inaccurate poses: the coarse pass from images when the poses are
too poor to guide matching (:mod:`.coarse_poses`), depth priors from data (:mod:`.depth_priors`), and the
guided-mapping stages (:mod:`.guided_mapping`); each reported pose tested against the images
(:mod:`.pose_checks`, with :mod:`.leave_one_out`, :mod:`.variance_factor`, :mod:`.gate_loss`); image-only
mapping inside a cavity (:mod:`.cavity_mapping`, :mod:`.cavity_map_choice`); a side-view quadrant with the
stage's poses (:mod:`.quadrant_mapping`); scan planning (:mod:`.scan_planning`); a map's self-check
(:mod:`.model_checks`); fused pose bounds (:mod:`.pose_fusion`); localization (:mod:`.localization`) and a
tool's approach path (:mod:`.approach`).
"""
