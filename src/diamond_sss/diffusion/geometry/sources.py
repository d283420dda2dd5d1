"""The four geometry sources: stored maps, a Gaussian reconstruction, Depth Anything v2, Marigold normals.

Only the first two know metric depth (:attr:`GeometryMaps.depth`); the monocular models give relative depth.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor

from diamond_sss.data.conventions import linear_to_srgb
from diamond_sss.data.dataset import OLATDataset
from diamond_sss.diffusion.common.hashing import files_hash, state_dict_hash
from diamond_sss.diffusion.geometry.base import (
    GeometryError,
    GeometryMaps,
    GeometrySource,
    depth_to_nearness,
    normalized_nearness,
    normals_from_nearness,
    world_to_camera_normals,
)

IMAGENET_MEAN = (0.485, 0.456, 0.406)
IMAGENET_STD = (0.229, 0.224, 0.225)


def _camera_maps(depth: Tensor, normals_world: Tensor, mask: Tensor, w2c: Tensor) -> GeometryMaps:
    keep = (mask > 0.5).to(depth.dtype)
    normals = world_to_camera_normals(normals_world[None], w2c[None])[0] * keep
    return GeometryMaps(nearness=depth_to_nearness(depth, mask), normals=normals, mask=mask, depth=depth)


def _require_dir(path: Path, what: str) -> Path:
    if not path.is_dir():
        raise GeometryError(
            f"{what} model path {path} does not exist (models are loaded from local folders only)"
        )
    return path


class StoredMapsGeometry(GeometrySource):
    """Depth and world-normal maps stored with the data (``depth_path`` / ``normal_path`` per frame)."""

    def maps(self, dataset: OLATDataset, view: int, image: Tensor, mask: Tensor) -> GeometryMaps:
        depth, normals = self._stored(dataset, view)
        return _camera_maps(depth, normals, mask, dataset.viewmats[view])

    def key(self) -> dict:
        return {"kind": "maps"}

    def view_key(self, dataset: OLATDataset, view: int) -> dict:
        """:meth:`key` and the content hash of the view's stored depth and normal maps (as :meth:`maps` reads them)."""
        depth, normals = self._stored(dataset, view)
        return {**self.key(), "maps": state_dict_hash({"depth": depth, "normals": normals})}

    @staticmethod
    def _stored(dataset: OLATDataset, view: int) -> tuple[Tensor, Tensor]:
        if not dataset.has_geometry_maps(view):
            raise GeometryError(
                f"{dataset.json_path}: view {view} has no stored depth/normal maps; "
                "use a reconstruction run folder or depth-anything:/marigold: models"
            )
        return dataset.load_geometry_maps(view)


class RenderedGeometry(GeometrySource):
    """Depth and normals rendered from a trained Gaussian reconstruction (run folder) at the view's camera."""

    def __init__(self, run: Path, device: str = "cpu") -> None:
        if not (Path(run) / "model.safetensors").is_file():
            raise GeometryError(f"{run} is not a finished reconstruction run (no model.safetensors)")
        self.run = Path(run)
        self.device = device
        self._scene = None

    def maps(self, dataset: OLATDataset, view: int, image: Tensor, mask: Tensor) -> GeometryMaps:
        from diamond_sss.runs.folder import load_scene

        if self._scene is None:
            self._scene = load_scene(self.run, self.device)[0].eval()
        camera = dataset.cameras[view]
        viewmat = dataset.viewmats[view][None].to(self.device)
        with torch.no_grad():
            render = self._scene.render(
                viewmat,
                dataset.intrinsics[view][None].to(self.device),
                camera.width,
                camera.height,
                dataset.light_positions[:1].to(self.device),
                dataset.light_intensities[:1].to(self.device),
            )
        gbuffer = render.gbuffer
        depth = (gbuffer.depth[0] * (gbuffer.alpha[0] > 0.5)).cpu()
        return _camera_maps(depth, gbuffer.normal[0].cpu(), mask, dataset.viewmats[view])

    def key(self) -> dict:
        return {"kind": "rendered", "hash": files_hash(self.run / "model.safetensors")}


class DepthAnythingGeometry(GeometrySource):
    """Depth Anything v2 (transformers ``AutoModelForDepthEstimation``) from a local folder.

    Its relative disparity is normalised to nearness over the mask; normals come from the nearness
    gradients (:func:`normals_from_nearness`). The image is resized to ``input_size`` (a multiple of 14).
    """

    def __init__(self, path: Path, device: str = "cpu", input_size: int = 518) -> None:
        if input_size % 14 != 0:
            raise ValueError(f"Depth Anything input size must be a multiple of 14, got {input_size}")
        self.path = _require_dir(Path(path), "Depth Anything")
        self.device = device
        self.input_size = input_size
        self._model = None

    def disparity(self, image: Tensor) -> Tensor:
        """Relative disparity ``[H,W,1]`` of a linear image ``[H,W,3]``."""
        from transformers import AutoModelForDepthEstimation

        if self._model is None:
            self._model = AutoModelForDepthEstimation.from_pretrained(self.path, local_files_only=True)
            self._model = self._model.to(self.device).eval()
        height, width = image.shape[:2]
        pixels = linear_to_srgb(image.clamp(0, 1)).permute(2, 0, 1)[None]
        pixels = F.interpolate(
            pixels, size=(self.input_size, self.input_size), mode="bicubic", align_corners=False
        )
        mean = torch.tensor(IMAGENET_MEAN).reshape(1, 3, 1, 1)
        std = torch.tensor(IMAGENET_STD).reshape(1, 3, 1, 1)
        with torch.no_grad():
            out = self._model(pixel_values=((pixels - mean) / std).to(self.device)).predicted_depth
        out = F.interpolate(
            out.reshape(1, 1, *out.shape[-2:]).float().cpu(),
            size=(height, width),
            mode="bilinear",
            align_corners=False,
        )
        return out[0].permute(1, 2, 0)

    def maps(self, dataset: OLATDataset, view: int, image: Tensor, mask: Tensor) -> GeometryMaps:
        nearness = normalized_nearness(self.disparity(image), mask)
        return GeometryMaps(nearness=nearness, normals=normals_from_nearness(nearness, mask), mask=mask)

    def key(self) -> dict:
        return {"kind": "depth-anything", "hash": files_hash(self.path), "input_size": self.input_size}


class MarigoldGeometry(GeometrySource):
    """Marigold normals (diffusers ``MarigoldNormalsPipeline``) from a local folder.

    Marigold's frame (x right, y up, z towards the viewer) is turned into OpenCV's (x, -y, -z). Alone it
    gives no depth: the nearness channel is then the mask (flat). Combine it with Depth Anything for both.
    """

    def __init__(self, path: Path, device: str = "cpu", seed: int = 0, steps: int | None = None) -> None:
        self.path = _require_dir(Path(path), "Marigold")
        self.device = device
        self.seed = seed
        self.steps = steps
        self._pipe = None

    def normals(self, image: Tensor) -> Tensor:
        """Unit camera-space (OpenCV) normals ``[H,W,3]`` of a linear image ``[H,W,3]``."""
        from diffusers import MarigoldNormalsPipeline

        if self._pipe is None:
            missing = {
                name: None for name in ("text_encoder", "tokenizer") if not (self.path / name).is_dir()
            }
            pipe = MarigoldNormalsPipeline.from_pretrained(self.path, local_files_only=True, **missing)
            if pipe.text_encoder is None:
                dim = pipe.unet.config.cross_attention_dim
                pipe.empty_text_embedding = torch.zeros(1, 2, dim)
            self._pipe = pipe.to(self.device)
            self._pipe.set_progress_bar_config(disable=True)
        srgb = linear_to_srgb(image.clamp(0, 1)).permute(2, 0, 1)[None].to(self.device)
        generator = torch.Generator(device="cpu").manual_seed(self.seed)
        out = self._pipe(
            srgb,
            num_inference_steps=self.steps,
            generator=generator,
            output_type="pt",
            match_input_resolution=True,
        )
        prediction = torch.as_tensor(
            np.asarray(out.prediction.cpu() if isinstance(out.prediction, Tensor) else out.prediction)
        ).float()
        normals = prediction.reshape(-1, *prediction.shape[-3:])[0]
        if normals.shape[0] == 3:
            normals = normals.permute(1, 2, 0)
        flip = torch.tensor([1.0, -1.0, -1.0])
        return F.normalize(normals * flip, dim=-1)

    def maps(self, dataset: OLATDataset, view: int, image: Tensor, mask: Tensor) -> GeometryMaps:
        keep = (mask > 0.5).to(image.dtype)
        return GeometryMaps(nearness=keep, normals=self.normals(image) * keep, mask=mask)

    def key(self) -> dict:
        return {"kind": "marigold", "hash": files_hash(self.path), "seed": self.seed, "steps": self.steps}


class CombinedGeometry(GeometrySource):
    """Nearness from Depth Anything, normals from Marigold (the paper's pairing)."""

    def __init__(self, depth: DepthAnythingGeometry, normals: MarigoldGeometry) -> None:
        self.depth = depth
        self.normal_source = normals

    def maps(self, dataset: OLATDataset, view: int, image: Tensor, mask: Tensor) -> GeometryMaps:
        nearness = normalized_nearness(self.depth.disparity(image), mask)
        keep = (mask > 0.5).to(image.dtype)
        return GeometryMaps(nearness=nearness, normals=self.normal_source.normals(image) * keep, mask=mask)

    def key(self) -> dict:
        return {"kind": "combined", "depth": self.depth.key(), "normals": self.normal_source.key()}
