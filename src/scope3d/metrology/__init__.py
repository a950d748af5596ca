"""Measurement against truth and of targets: errors against ground truth (:mod:`.evaluation`) and
fluorescent targets on the surface (:mod:`.fluorescence`). The thread gauge lands here too.
"""
