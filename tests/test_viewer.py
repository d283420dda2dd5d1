"""Web viewer: camera conversion against the data conventions, light placement, frames equal to the renderer's."""

from __future__ import annotations

import math
import socket

import numpy as np
import pytest
import torch

from diamond_sss.data.conventions import look_at_opengl_c2w, opengl_c2w_to_opencv_w2c
from diamond_sss.data.images import to_srgb8
from diamond_sss.gaussians.model import GaussianModel
from diamond_sss.scene.model import RelightableScene
from diamond_sss.viewer import (
    ViewSettings,
    light_from_angles,
    render_frame,
    view_intrinsics,
    viser_camera_to_w2c,
)


def rotation_to_wxyz(matrix: np.ndarray) -> np.ndarray:
    """Quaternion of a rotation matrix (viser's SO3, independent of the code under test)."""
    transforms = pytest.importorskip("viser.transforms", reason="needs viser (the 'viewer' extra)")
    return transforms.SO3.from_matrix(matrix).wxyz


def small_scene() -> RelightableScene:
    g = torch.Generator().manual_seed(0)
    points = torch.randn(300, 3, generator=g) * 0.3
    model = GaussianModel.from_points(points, torch.rand(300, 3, generator=g), None, generator=g)
    return RelightableScene(
        model, sss_width=16, light_init=0.0, scene_center=torch.zeros(3), scene_radius=0.5
    )


def test_viser_camera_matches_the_data_convention():
    eye, target = torch.tensor([1.0, -2.0, 1.5]), torch.tensor([0.1, 0.2, -0.1])
    w2c = opengl_c2w_to_opencv_w2c(look_at_opengl_c2w(eye, target)).double()
    c2w = torch.linalg.inv(w2c).numpy()  # OpenCV camera-to-world: viser's P_world = R P_camera + t
    converted = viser_camera_to_w2c(rotation_to_wxyz(c2w[:3, :3]), c2w[:3, 3])
    assert torch.allclose(converted, w2c.float(), atol=1e-5)
    # The target lies straight ahead: camera x = y = 0, z = distance.
    ahead = converted[:3, :3] @ target + converted[:3, 3]
    assert torch.allclose(ahead, torch.tensor([0.0, 0.0, float((target - eye).norm())]), atol=1e-5)


def test_intrinsics_and_light_known_answers():
    K, width, height = view_intrinsics(math.pi / 2, 1.5, 100)
    assert (width, height) == (150, 100)
    assert torch.allclose(K, torch.tensor([[50.0, 0, 75.0], [0, 50.0, 50.0], [0, 0, 1]]), atol=1e-4)
    with pytest.raises(ValueError, match="field of view"):
        view_intrinsics(0.0, 1.0, 10)
    settings = ViewSettings(azimuth_deg=90.0, elevation_deg=0.0, distance_radii=3.0)
    assert torch.allclose(
        light_from_angles(torch.tensor([1.0, 0, 0]), 2.0, settings), torch.tensor([1.0, 6.0, 0]), atol=1e-5
    )
    up = ViewSettings(elevation_deg=90.0, distance_radii=2.0)
    assert torch.allclose(
        light_from_angles(torch.zeros(3), 1.0, up), torch.tensor([0.0, 0.0, 2.0]), atol=1e-5
    )


def test_frame_is_the_renderers_image_and_channels_differ():
    scene = small_scene().eval()
    w2c = opengl_c2w_to_opencv_w2c(look_at_opengl_c2w(torch.tensor([0.0, -2.5, 0.5]), torch.zeros(3))).float()
    K, width, height = view_intrinsics(math.radians(40.0), 1.0, 24)
    settings = ViewSettings(
        azimuth_deg=-60.0, elevation_deg=20.0, intensity=2.0, overrides={"roughness": 0.3}
    )
    frame = render_frame(scene, w2c, K, width, height, settings)
    with torch.no_grad():
        light = light_from_angles(scene.scene_center, 0.5, settings)
        expected = scene.render(
            w2c[None],
            K[None],
            width,
            height,
            light[None],
            torch.full((1, 3), 2.0),
            overrides={"roughness": 0.3},
        ).radiance[0]
    assert frame.shape == (24, 24, 3) and frame.dtype == np.uint8
    assert np.array_equal(frame, to_srgb8(expected)) and frame.max() > 0
    normals = render_frame(scene, w2c, K, width, height, ViewSettings(channel="normal"))
    assert normals.shape == frame.shape and not np.array_equal(normals, frame)
    with pytest.raises(ValueError, match="unknown channel"):
        render_frame(scene, w2c, K, width, height, ViewSettings(channel="albedo"))


def test_server_builds_its_gui_and_follows_it():
    viser = pytest.importorskip("viser", reason="needs viser (the 'viewer' extra)")
    from diamond_sss.viewer.server import SceneViewer

    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        port = probe.getsockname()[1]
    server = viser.ViserServer(host="127.0.0.1", port=port, verbose=False)
    try:
        viewer = SceneViewer(server, small_scene(), resolution=16)
        viewer.material_toggles["subsurface"].value = True
        viewer.material_values["subsurface"].value = 0.9
        viewer.azimuth.value = 90.0
        settings = viewer.settings()
        assert settings.overrides == {"subsurface": 0.9} and settings.azimuth_deg == 90.0
        assert np.allclose(
            viewer.light_marker.position,
            [0.0, 4.0 * 0.5 * math.cos(math.radians(30.0)), 4.0 * 0.5 * math.sin(math.radians(30.0))],
            atol=1e-4,
        )
        image = viewer.frame(np.array([1.0, 0, 0, 0]), np.array([0.0, 0.0, -2.0]), math.radians(50.0), 1.0)
        assert image.shape == (16, 16, 3)
        assert viewer.refresh() == 0  # no browser connected: nothing to render
    finally:
        server.stop()


def test_loopback_hosts_and_urls():
    pytest.importorskip("viser", reason="needs viser (the 'viewer' extra)")
    from diamond_sss.viewer.server import is_loopback, viewer_url

    assert is_loopback("127.0.0.1") and is_loopback("localhost") and is_loopback("::1")
    assert not is_loopback("0.0.0.0") and not is_loopback("192.168.1.4") and not is_loopback("example.org")
    assert viewer_url("127.0.0.1", 8080) == "http://127.0.0.1:8080"
    assert viewer_url("::1", 9000) == "http://[::1]:9000"


@pytest.mark.parametrize("host, warned", [(None, False), ("0.0.0.0", True)])
def test_serve_binds_loopback_by_default_and_warns_when_exposed(monkeypatch, capsys, caplog, host, warned):
    pytest.importorskip("viser", reason="needs viser (the 'viewer' extra)")
    from diamond_sss.runs import folder as run_folder
    from diamond_sss.viewer import server as server_module

    bound = {}

    class FakeServer:
        def __init__(self, host, port):
            bound["host"] = host

        def get_port(self):
            return 8123

        def stop(self):
            bound["stopped"] = True

    class InterruptedViewer:
        def __init__(self, *args):
            pass

        def refresh(self):
            raise KeyboardInterrupt

    monkeypatch.setattr(run_folder, "load_scene", lambda run, device: (small_scene(), None))
    monkeypatch.setattr(server_module.viser, "ViserServer", FakeServer)
    monkeypatch.setattr(server_module, "SceneViewer", InterruptedViewer)
    kwargs = {} if host is None else {"host": host}
    server_module.serve("run", device="cpu", **kwargs)
    expected = host or "127.0.0.1"
    assert bound == {"host": expected, "stopped": True}
    assert f"http://{expected}:8123" in capsys.readouterr().out
    warnings = [r.getMessage() for r in caplog.records if r.levelname == "WARNING"]
    assert bool(warnings) == warned and all("0.0.0.0" in w for w in warnings)
