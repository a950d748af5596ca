"""scope3d: metric 3D models from a robot-held scope whose poses are known within a tolerance.

Layers, lowest first (a layer imports only its own and lower ones; docs/architecture.md names every module):
:mod:`.errors`, :mod:`.utils` -> :mod:`.geometry` -> :mod:`.sensor` -> :mod:`.scene` -> :mod:`.io` ->
:mod:`.phantoms` -> :mod:`.feature` -> :mod:`.estimators` -> :mod:`.sfm`, :mod:`.mvs`, :mod:`.registration`,
:mod:`.metrology` -> :mod:`.pipelines` -> :mod:`.report` -> :mod:`.cli`.
"""
from scope3d.errors import InputError

__version__ = "0.1.0"

# The NumPy/SciPy-backed types load on first use (PEP 562), so that ``scope3d --version`` and ``--help``
# start without importing SciPy.
_LAZY = {"Camera": "scope3d.sensor.camera", "MeasuredPose": "scope3d.sensor.pose_tolerance",
         "Pose": "scope3d.geometry.pose", "PoseTolerance": "scope3d.sensor.pose_tolerance"}


def __getattr__(name: str):
    if name in _LAZY:
        import importlib

        return getattr(importlib.import_module(_LAZY[name]), name)
    raise AttributeError(f"module 'scope3d' has no attribute {name!r}")

__all__ = ["Camera", "InputError", "MeasuredPose", "Pose", "PoseTolerance", "__version__"]
