"""Helpers every layer may use: atomic outputs (:mod:`.atomic`).
"""
