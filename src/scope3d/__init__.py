"""scope3d: metric 3D models from a robot-held scope whose poses are known within a tolerance.

Layers, lowest first (a lower layer never imports a higher one):
``geometry`` -> ``pose``, ``camera`` -> ``dataset``/``formats``, ``phantoms`` -> features, bundle adjustment
-> stereo, registration, metrology -> ``pipelines`` -> ``cli``.
"""
from scope3d.errors import InputError
from scope3d.geometry.pose import Pose
from scope3d.sensor.camera import Camera
from scope3d.sensor.pose_tolerance import MeasuredPose, PoseTolerance

__version__ = "0.1.0"

__all__ = ["Camera", "InputError", "MeasuredPose", "Pose", "PoseTolerance", "__version__"]
