"""LPIPS (Zhang et al. 2018, v0.1, VGG16 "lin" variant) in pure PyTorch, weights from a local file only.

``LPIPS(x, y) = sum_l mean_{h,w} w_l . (f^l_x / ||f^l_x|| - f^l_y / ||f^l_y||)^2`` with ``f^l`` the VGG16
activations relu1_2, relu2_2, relu3_3, relu4_3, relu5_3 (channel-normalised, ``eps = 1e-10``) and
``w_l >= 0`` the 1x1 "lin" weights. Inputs are sRGB in ``[0, 1]``, mapped to ``[-1, 1]`` and then
through LPIPS's scaling layer ``(x - shift) / scale``.

Nothing is downloaded. The weights come from a safetensors file (argument, or the environment
variable ``DIAMOND_SSS_LPIPS_WEIGHTS``) with exactly these keys:

* ``vgg.conv{s}_{i}.weight`` / ``.bias`` for the 13 VGG16 convolutions (``conv1_1`` ... ``conv5_3``),
  torchvision ``features.{0,2,5,7,10,12,14,17,19,21,24,26,28}`` in that order;
* ``lin.{l}.weight`` of shape ``[1, C_l, 1, 1]`` for ``l = 0..4`` (``C = 64, 128, 256, 512, 512``),
  the official ``lin{l}.model.1.weight`` of ``lpips/weights/v0.1/vgg.pth``.

:func:`convert_lpips_state_dict` maps the official torchvision / lpips state dicts to these names::

    sd = convert_lpips_state_dict(torchvision_vgg16.state_dict(), torch.load("vgg.pth"))
    safetensors.torch.save_file(sd, "lpips_vgg.safetensors")
"""

from __future__ import annotations

import logging
import os
import re
from pathlib import Path

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from diamond_sss.utils.io import load_safetensors
from diamond_sss.utils.logs import warn_once

logger = logging.getLogger(__name__)

WEIGHTS_ENV_VAR = "DIAMOND_SSS_LPIPS_WEIGHTS"

# (name, in_channels, out_channels, torchvision ``features`` index) of the 13 VGG16 convolutions.
VGG16_CONVS: tuple[tuple[str, int, int, int], ...] = (
    ("conv1_1", 3, 64, 0),
    ("conv1_2", 64, 64, 2),
    ("conv2_1", 64, 128, 5),
    ("conv2_2", 128, 128, 7),
    ("conv3_1", 128, 256, 10),
    ("conv3_2", 256, 256, 12),
    ("conv3_3", 256, 256, 14),
    ("conv4_1", 256, 512, 17),
    ("conv4_2", 512, 512, 19),
    ("conv4_3", 512, 512, 21),
    ("conv5_1", 512, 512, 24),
    ("conv5_2", 512, 512, 26),
    ("conv5_3", 512, 512, 28),
)
# The five stages; each ends at the tapped ReLU (relu1_2 ... relu5_3); stages 2-5 start with a max-pool.
VGG16_STAGES: tuple[tuple[str, ...], ...] = (
    ("conv1_1", "conv1_2"),
    ("conv2_1", "conv2_2"),
    ("conv3_1", "conv3_2", "conv3_3"),
    ("conv4_1", "conv4_2", "conv4_3"),
    ("conv5_1", "conv5_2", "conv5_3"),
)
LIN_CHANNELS: tuple[int, ...] = (64, 128, 256, 512, 512)
# LPIPS scaling layer constants (inputs in [-1, 1]).
_SHIFT = (-0.030, -0.088, -0.188)
_SCALE = (0.458, 0.448, 0.450)
_NORM_EPS = 1e-10


def expected_shapes() -> dict[str, tuple[int, ...]]:
    """Key -> shape of every tensor an LPIPS weights file must contain."""
    shapes: dict[str, tuple[int, ...]] = {}
    for name, c_in, c_out, _ in VGG16_CONVS:
        shapes[f"vgg.{name}.weight"] = (c_out, c_in, 3, 3)
        shapes[f"vgg.{name}.bias"] = (c_out,)
    for index, channels in enumerate(LIN_CHANNELS):
        shapes[f"lin.{index}.weight"] = (1, channels, 1, 1)
    return shapes


class LPIPS(nn.Module):
    """LPIPS v0.1 distance with a VGG16 backbone; frozen, call ``.to(device)`` as needed.

    ``forward(pred, target)``: sRGB images ``[B,H,W,3]`` in ``[0, 1]`` -> distance ``[B]`` (>= 0).
    """

    def __init__(self) -> None:
        super().__init__()
        self.vgg = nn.ModuleDict(
            {name: nn.Conv2d(c_in, c_out, kernel_size=3, padding=1) for name, c_in, c_out, _ in VGG16_CONVS}
        )
        self.lin = nn.ModuleList(nn.Conv2d(c, 1, kernel_size=1, bias=False) for c in LIN_CHANNELS)
        self.register_buffer("shift", torch.tensor(_SHIFT).view(1, 3, 1, 1), persistent=False)
        self.register_buffer("scale", torch.tensor(_SCALE).view(1, 3, 1, 1), persistent=False)
        self.requires_grad_(False)
        self.eval()

    def features(self, images: Tensor) -> list[Tensor]:
        """VGG16 activations relu1_2 ... relu5_3 of NCHW images already in LPIPS's input space."""
        taps = []
        x = images
        for stage_index, stage in enumerate(VGG16_STAGES):
            if stage_index > 0:
                x = F.max_pool2d(x, kernel_size=2, stride=2)
            for name in stage:
                x = F.relu(self.vgg[name](x))
            taps.append(x)
        return taps

    def forward(self, pred: Tensor, target: Tensor) -> Tensor:
        if pred.ndim != 4 or pred.shape[-1] != 3 or pred.shape != target.shape:
            raise ValueError(
                f"LPIPS expects two [B,H,W,3] images of equal shape, "
                f"got {tuple(pred.shape)} and {tuple(target.shape)}"
            )
        batch = pred.shape[0]
        both = torch.cat([pred, target], dim=0).permute(0, 3, 1, 2).to(self.shift.dtype)
        both = ((both * 2.0 - 1.0) - self.shift) / self.scale
        distance = pred.new_zeros(batch, dtype=both.dtype)
        for feature, lin in zip(self.features(both), self.lin):
            normalised = feature / (feature.square().sum(dim=1, keepdim=True).sqrt() + _NORM_EPS)
            difference = (normalised[:batch] - normalised[batch:]).square()
            distance = distance + lin(difference).mean(dim=(1, 2, 3))
        return distance


def convert_lpips_state_dict(
    vgg_state_dict: dict[str, Tensor], lin_state_dict: dict[str, Tensor]
) -> dict[str, Tensor]:
    """Official weights -> this module's key names (see the module docstring).

    ``vgg_state_dict``: torchvision ``vgg16().state_dict()`` (``features.{idx}.weight``; classifier keys
    are ignored) or the ``net.slice{k}.{idx}.*`` keys of an ``lpips.LPIPS`` state dict.
    ``lin_state_dict``: lpips ``vgg.pth`` (``lin{l}.model.1.weight``; ``model.0`` without dropout).
    Raises ``KeyError`` naming the first missing key.
    """
    by_index: dict[str, Tensor] = {}
    for key, value in vgg_state_dict.items():
        match = re.fullmatch(r"(?:features|net\.slice\d)\.(\d+)\.(weight|bias)", key)
        if match:
            by_index[f"{match.group(1)}.{match.group(2)}"] = value
    lin_by_index: dict[int, Tensor] = {}
    for key, value in lin_state_dict.items():
        match = re.fullmatch(r"lin(\d)\.model\.\d\.weight", key)
        if match:
            lin_by_index[int(match.group(1))] = value
    converted: dict[str, Tensor] = {}
    for name, _, _, index in VGG16_CONVS:
        for kind in ("weight", "bias"):
            source = f"{index}.{kind}"
            if source not in by_index:
                raise KeyError(f"VGG16 state dict lacks 'features.{source}' (needed for vgg.{name}.{kind})")
            converted[f"vgg.{name}.{kind}"] = by_index[source].detach().clone().contiguous()
    for index in range(len(LIN_CHANNELS)):
        if index not in lin_by_index:
            raise KeyError(f"LPIPS lin state dict lacks 'lin{index}.model.1.weight'")
        converted[f"lin.{index}.weight"] = lin_by_index[index].detach().clone().contiguous()
    return converted


def _read_weights(path: Path) -> dict[str, Tensor]:
    state = load_safetensors(path)
    shapes = expected_shapes()
    for key in state:
        if key not in shapes:
            raise ValueError(f"LPIPS weights file {path} has unexpected key '{key}'")
    for key, shape in shapes.items():
        if key not in state:
            raise ValueError(f"LPIPS weights file {path} lacks key '{key}' (shape {list(shape)})")
        if tuple(state[key].shape) != shape:
            raise ValueError(
                f"LPIPS weights file {path}: key '{key}' has shape {list(state[key].shape)}, "
                f"expected {list(shape)}"
            )
        if key.startswith("lin.") and bool((state[key] < 0).any()):
            raise ValueError(
                f"LPIPS weights file {path}: key '{key}' has negative weights (LPIPS lin is >= 0)"
            )
    return state


def load_lpips(path: str | os.PathLike[str] | None = None) -> LPIPS | None:
    """LPIPS network with weights from ``path`` (or ``$DIAMOND_SSS_LPIPS_WEIGHTS``), or None.

    Returns None, with one warning line per process, when no path is given or the file
    does not exist; never downloads. A file with missing, unexpected or misshaped keys raises
    ``ValueError`` naming the file and the key.
    """
    if path is None:
        path = os.environ.get(WEIGHTS_ENV_VAR) or None
    if path is None:
        warn_once(logger, "lpips", "LPIPS is disabled: no weights file given and $%s is not set",
                  WEIGHTS_ENV_VAR)
        return None
    weights_path = Path(path)
    if not weights_path.is_file():
        warn_once(logger, "lpips", "LPIPS is disabled: weights file %s does not exist", weights_path)
        return None
    model = LPIPS()
    model.load_state_dict(_read_weights(weights_path))
    return model
