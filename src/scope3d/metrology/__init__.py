"""Measurement against truth and of targets: errors against ground truth (:mod:`.evaluation`), fluorescent
targets on the surface (:mod:`.fluorescence`), physical scale from star targets (:mod:`.star_scale`), a
textured wall against the true albedo (:mod:`.texture_evaluation`), the virtual ISO thread gauge
(:mod:`.thread_gauge`), its ISO 965-1 limits (:mod:`.thread_tolerances`), its uncertainty
(:mod:`.thread_uncertainty`) and a hole's scan plan (:mod:`.thread_scan_plan`).
"""
