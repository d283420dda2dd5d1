"""Interactive web viewer of a trained run (viser): orbit the object, move the light, edit materials."""

from diamond_sss.viewer.frame import (
    CHANNELS,
    ViewSettings,
    light_from_angles,
    render_frame,
    view_intrinsics,
    viser_camera_to_w2c,
)

__all__ = [
    "CHANNELS",
    "ViewSettings",
    "light_from_angles",
    "render_frame",
    "view_intrinsics",
    "viser_camera_to_w2c",
]
