"""What every 3D page draws the same way: the camera's start and the end-effector markers.

The live session (teleop.web.session_page.drawing) and the replay viewer (teleop.web.replay_page.viewer)
both start their camera here and draw the same markers, so a recorded episode looks as it did live. The
browser tests project world points through the same camera numbers.
"""

from __future__ import annotations

import numpy as np
import trimesh
import viser

from teleop.web.viser_internals.scene_stream import set_arrays

EE_COLOR = (255, 140, 0)
ERROR_COLOR = (255, 60, 60)
CAMERA_POSITION = (1.45, -1.05, 0.95)  # m, world frame (z up)
CAMERA_LOOK_AT = (0.35, 0.0, 0.2)  # m, world frame
CAMERA_FOV = np.radians(50.0)  # vertical


def place_camera(server: viser.ViserServer) -> None:
    """viser's initial camera (world frame, z up) for every page of ours; the browser tests
    project world points through the same numbers."""
    server.initial_camera.position = CAMERA_POSITION
    server.initial_camera.look_at = CAMERA_LOOK_AT
    server.initial_camera.up = (0.0, 0.0, 1.0)
    server.initial_camera.fov = CAMERA_FOV


class Markers:
    """Per arm: the target frame (axes), the actual end effector (an orange ball) and a red line
    between them, in the world frame (m)."""

    def __init__(self, server: viser.ViserServer, n_arms: int) -> None:
        n = n_arms
        self.target_axes = server.scene.add_batched_axes(
            "/markers/targets", batched_wxyzs=np.tile([1.0, 0, 0, 0], (n, 1)), batched_positions=np.zeros((n, 3)),
            axes_length=0.05, axes_radius=0.003,
        )
        ball = trimesh.creation.icosphere(subdivisions=2, radius=0.012)
        self.ee_balls = server.scene.add_batched_meshes_simple(
            "/markers/ee", ball.vertices, ball.faces, batched_wxyzs=np.tile([1.0, 0, 0, 0], (n, 1)),
            batched_positions=np.zeros((n, 3)), batched_colors=np.tile(EE_COLOR, (n, 1)).astype(np.uint8),
            lod="off", cast_shadow=False, receive_shadow=False,
        )
        self.error_lines = server.scene.add_line_segments(
            "/markers/error", points=np.zeros((n, 2, 3)), colors=np.tile(ERROR_COLOR, (n, 2, 1)).astype(np.uint8),
            thickness=3.0, thickness_units="screen",
        )

    def draw(self, targets: np.ndarray, ee: np.ndarray) -> None:
        """targets: (n_arms, 7) position + wxyz; ee: (n_arms, >=3), the position first."""
        set_arrays(self.target_axes, batched_positions=targets[:, :3], batched_wxyzs=targets[:, 3:7])
        set_arrays(self.ee_balls, batched_positions=ee[:, :3])
        set_arrays(self.error_lines, points=np.stack([ee[:, :3], targets[:, :3]], axis=1))
