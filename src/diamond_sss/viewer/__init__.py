"""Interactive web viewer of a trained run (viser): orbit the object, move the light, edit materials."""

from diamond_sss.viewer.frame import (
    CHANNELS,
    ViewSettings,
    intrinsics_from_fov,
    light_from_angles,
    render_frame,
    viser_camera_to_w2c,
)

__all__ = [
    "CHANNELS",
    "ViewSettings",
    "intrinsics_from_fov",
    "light_from_angles",
    "render_frame",
    "viser_camera_to_w2c",
]
