"""Helpers every layer may use: atomic outputs (:mod:`.atomic`), JSON with numpy values (:mod:`.jsonio`).
"""
