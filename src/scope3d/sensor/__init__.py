"""What the hardware gives: the camera and its lens models (:mod:`.camera`, :mod:`.camera_models`), the
robot's measured poses with their tolerance (:mod:`.pose_tolerance`), calibration from boards with
covariance (:mod:`.calibration`), a fitted distortion field (:mod:`.distortion_field`) and the camera's
pose on the robot's flange (:mod:`.hand_eye`).
"""
from scope3d.sensor.camera import Camera
from scope3d.sensor.pose_tolerance import CABLE_DRIVEN_ARM, MICRO_STAGE, OPTICAL_TRACKER, MeasuredPose, PoseTolerance

__all__ = ["CABLE_DRIVEN_ARM", "Camera", "MICRO_STAGE", "MeasuredPose", "OPTICAL_TRACKER", "PoseTolerance"]
