"""Structure from motion with known-but-inaccurate poses: the coarse pass from images when the poses are
too poor to guide matching (:mod:`.coarse_poses`), depth priors from data (:mod:`.depth_priors`), and the
guided-mapping stages (:mod:`.guided_mapping`); each reported pose tested against the images
(:mod:`.pose_checks`, with :mod:`.leave_one_out`, :mod:`.variance_factor`, :mod:`.gate_loss`); image-only
mapping inside a cavity (:mod:`.cavity_mapping`, :mod:`.cavity_map_choice`); localization (:mod:`.localization`).
"""
