"""Structure from motion with known-but-inaccurate poses: the coarse pass from images when the poses are
too poor to guide matching (:mod:`.coarse_poses`), depth priors from data (:mod:`.depth_priors`), and the
guided-mapping stages (:mod:`.guided_mapping`). Image-only mapping and localization land here too.
"""
