"""Helpers every layer may use: atomic outputs (:mod:`.atomic`), JSON with numpy values (:mod:`.jsonio`),
figures on an Agg canvas without pyplot (:mod:`.figures`).
"""
