"""The robot's current pose on the map: a frame with axes and a small camera frustum.

The pose is the map pose ``l_current (+) offset``, the offset's heading with the odometry's estimated
bias taken off (:attr:`hippomap.cognitive_map.CognitiveMap.robot_pose_estimate`): where the corrected
trajectory ends. The frustum looks along the robot's heading (+x), like the
camera whose frames the panel shows.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from ..settings import ViewerSettings

POSE_Z = 0.1


def yaw_wxyz(theta: float) -> tuple[float, float, float, float]:
    """Quaternion (w, x, y, z) of a rotation by ``theta`` about +z."""
    return (math.cos(theta / 2), 0.0, 0.0, math.sin(theta / 2))


# camera looks along its local +z; rotate it to look along the robot's +x with image-down = -z
_CAMERA_WXYZ = (0.5, -0.5, 0.5, -0.5)


class RobotMarker:
    """Scene nodes ``/robot`` (frame) and ``/robot/camera`` (frustum)."""

    def __init__(self, scene: Any, settings: ViewerSettings) -> None:
        self.frame = scene.add_frame("/robot", axes_length=0.3, axes_radius=0.015, position=(0.0, 0.0, POSE_Z))
        self.camera = scene.add_camera_frustum(
            "/robot/camera",
            fov=math.radians(60.0),
            aspect=4 / 3,
            scale=0.25,
            color=settings.color_robot,
            wxyz=_CAMERA_WXYZ,
        )
        self._last: np.ndarray | None = None

    def update(self, pose: np.ndarray) -> bool:
        """Move to ``pose`` (x, y, theta); returns whether anything was sent."""
        pose = np.asarray(pose, float)
        if self._last is not None and np.allclose(pose, self._last, atol=1e-3):
            return False
        self.frame.position = (float(pose[0]), float(pose[1]), POSE_Z)
        self.frame.wxyz = yaw_wxyz(float(pose[2]))
        self._last = pose.copy()
        return True

    @property
    def visible(self) -> bool:
        return bool(self.frame.visible)

    @visible.setter
    def visible(self, value: bool) -> None:
        self.frame.visible = bool(value)
