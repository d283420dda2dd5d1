"""``diamond-sss view``: a viser web server that renders the trained scene from the browser's camera.

Every frame is the real deferred SSS render (``frame.render_frame``) sent as the scene's background image; the
GUI moves the point light, sets its intensity, picks the shown channel and overrides materials. A frame is
re-rendered only when the client's camera or the GUI changed.
"""

from __future__ import annotations

import ipaddress
import logging
import time
from pathlib import Path

import numpy as np
import viser

from diamond_sss.scene.model import RelightableScene
from diamond_sss.viewer.frame import (
    CHANNELS,
    ViewSettings,
    light_from_angles,
    render_frame,
    view_intrinsics,
    viser_camera_to_w2c,
)

logger = logging.getLogger(__name__)

MATERIALS = {"roughness": 0.5, "metallic": 0.0, "subsurface": 0.5}
"""Materials the GUI can override, with the slider's initial value."""


class SceneViewer:
    """GUI handles on a :class:`viser.ViserServer` and the render loop of one trained scene."""

    def __init__(self, server: viser.ViserServer, scene: RelightableScene, resolution: int = 256) -> None:
        self.server, self.scene = server, scene.eval()
        self._version = 0
        self._shown: dict[int, tuple[float, int]] = {}
        gui = server.gui
        with gui.add_folder("Light"):
            self.azimuth = gui.add_slider(
                "azimuth (deg)", min=-180.0, max=180.0, step=1.0, initial_value=30.0
            )
            self.elevation = gui.add_slider(
                "elevation (deg)", min=-89.0, max=89.0, step=1.0, initial_value=30.0
            )
            self.distance = gui.add_slider("distance (radii)", min=1.2, max=10.0, step=0.1, initial_value=4.0)
            self.intensity = gui.add_slider("intensity", min=0.0, max=10.0, step=0.05, initial_value=1.0)
        with gui.add_folder("View"):
            self.channel = gui.add_dropdown("channel", CHANNELS, initial_value="radiance")
            self.resolution = gui.add_slider(
                "resolution (px)", min=16, max=1024, step=16, initial_value=resolution
            )
        self.material_toggles, self.material_values = {}, {}
        with gui.add_folder("Material overrides"):
            for name, initial in MATERIALS.items():
                self.material_toggles[name] = gui.add_checkbox(f"override {name}", initial_value=False)
                self.material_values[name] = gui.add_slider(
                    name, min=0.0, max=1.0, step=0.01, initial_value=initial
                )
        handles = [
            self.azimuth,
            self.elevation,
            self.distance,
            self.intensity,
            self.channel,
            self.resolution,
            *self.material_toggles.values(),
            *self.material_values.values(),
        ]
        for handle in handles:
            handle.on_update(self._changed)
        radius = float(scene.scene_radius)
        self.light_marker = server.scene.add_icosphere("light", radius=0.05 * radius, color=(255, 220, 80))
        self._place_light()
        server.on_client_connect(self._frame_object)

    def settings(self) -> ViewSettings:
        """The GUI's current :class:`ViewSettings`."""
        return ViewSettings(
            azimuth_deg=float(self.azimuth.value),
            elevation_deg=float(self.elevation.value),
            distance_radii=float(self.distance.value),
            intensity=float(self.intensity.value),
            channel=str(self.channel.value),
            overrides={
                name: float(self.material_values[name].value)
                for name, toggle in self.material_toggles.items()
                if toggle.value
            },
        )

    def frame(self, wxyz: np.ndarray, position: np.ndarray, fov_y: float, aspect: float) -> np.ndarray:
        """The image a client with this camera sees now (uint8 ``[H,W,3]``)."""
        K, width, height = view_intrinsics(fov_y, aspect, int(self.resolution.value))
        return render_frame(
            self.scene, viser_camera_to_w2c(wxyz, position), K, width, height, self.settings()
        )

    def refresh(self) -> int:
        """Re-render for every client whose camera or GUI changed since its last frame; returns how many."""
        rendered = 0
        for client_id, client in list(self.server.get_clients().items()):
            camera = client.camera
            state = (camera.update_timestamp, self._version)
            if camera.update_timestamp == 0.0 or self._shown.get(client_id) == state:
                continue
            image = self.frame(camera.wxyz, camera.position, camera.fov, camera.aspect)
            client.scene.set_background_image(image, format="jpeg")
            self._shown[client_id] = state
            rendered += 1
        return rendered

    def _changed(self, _event: object) -> None:
        self._version += 1
        self._place_light()

    def _place_light(self) -> None:
        position = light_from_angles(self.scene.scene_center, float(self.scene.scene_radius), self.settings())
        self.light_marker.position = tuple(float(v) for v in position)

    def _frame_object(self, client: viser.ClientHandle) -> None:
        center = self.scene.scene_center.detach().float().cpu().numpy()
        radius = float(self.scene.scene_radius)
        client.camera.up_direction = (0.0, 0.0, 1.0)
        client.camera.position = tuple(center + radius * np.array([3.0, -3.0, 1.5]))
        client.camera.look_at = tuple(center)


def is_loopback(host: str) -> bool:
    """Whether ``host`` (a name or an address) is reachable only from this machine."""
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


def viewer_url(host: str, port: int) -> str:
    """The URL of a server bound to ``host``:``port`` (IPv6 addresses in brackets)."""
    return f"http://[{host}]:{port}" if ":" in host else f"http://{host}:{port}"


def serve(
    run: Path,
    *,
    host: str = "127.0.0.1",
    port: int = 8080,
    resolution: int = 256,
    device: str = "auto",
    fps: float = 30.0,
) -> None:
    """Serve ``run`` at ``http://host:port`` until interrupted (Ctrl-C)."""
    from diamond_sss.runs.folder import load_scene
    from diamond_sss.utils.device import resolve_device

    scene, _ = load_scene(Path(run), resolve_device(device))
    if not is_loopback(host):
        logger.warning("viewer listens on %s: anyone who can reach this machine on port %d can drive it", host, port)
    server = viser.ViserServer(host=host, port=port)
    viewer = SceneViewer(server, scene, resolution)
    print(f"viewer of {run} at {viewer_url(host, server.get_port())} (Ctrl-C to stop)")
    try:
        while True:
            if viewer.refresh() == 0:
                time.sleep(1.0 / fps)
    except KeyboardInterrupt:
        server.stop()
