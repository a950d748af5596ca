"""Helpers every layer may use: atomic outputs (:mod:`.atomic`), JSON with numpy values (:mod:`.jsonio`),
figures on an Agg canvas without pyplot (:mod:`.figures`), robust scales and Huber weights (:mod:`.robust`),
the machine's cores (:mod:`.threads`) and BLAS threads (:mod:`.blas`).
"""
