"""Sparse features and their correspondences: detection (:mod:`.detection`), image retrieval
(:mod:`.retrieval`), which frames overlap (:mod:`.pairs`), the depth prior that predicts where a feature
reappears (:mod:`.depth_prior`), sparse matching (:mod:`.matching`, compiled :mod:`.descriptor_kernels`),
tracks from matches (:mod:`.tracks`), a video's key frames (:mod:`.keyframes`) and the matches' figures
(:mod:`.figures`).
"""
