"""``diamond-sss finetune-nvs | nvs``: fine-tune and run the novel-view diffusion model."""

from __future__ import annotations

import dataclasses
import typing
from pathlib import Path
from typing import Annotated

import tyro
from rich.console import Console

from diamond_sss.cli.options import config_from, options_of
from diamond_sss.diffusion.nvs.config import FinetuneConfig, NVSConfig

FinetuneOptions = options_of(FinetuneConfig, exclude=("model",))
MODEL_OPTIONS = ("space", "image_size", "prediction_type", "hint_residual", "block_out_channels", "layers_per_block")
"""The ``NVSConfig`` fields ``finetune-nvs`` takes on the command line."""


def model_options() -> type:
    """:func:`options_of` ``NVSConfig``'s :data:`MODEL_OPTIONS`, each defaulting to ``None``: not given, the
    ``--init-from`` model's value or else the config's default (which the help names)."""
    hints = typing.get_type_hints(NVSConfig)
    defaults = NVSConfig()
    specs = []
    for name in (f.name for f in dataclasses.fields(NVSConfig) if f.name in MODEL_OPTIONS):
        default = getattr(defaults, name)
        shown = " ".join(map(str, default)) if isinstance(default, tuple) else default
        hint = f"(default: the --init-from model's, else {shown})"
        specs.append((name, Annotated[hints[name] | None, tyro.conf.DisallowNone,
                                      tyro.conf.arg(help_behavior_hint=hint)], dataclasses.field(default=None)))
    options = dataclasses.make_dataclass("NVSConfigOptions", specs)
    options.__doc__ = NVSConfig.__doc__
    return options


NVSModelOptions = model_options()


def finetune_nvs(
    out: Path,
    data: list[Path] | None = None,
    warp_hint: bool | None = None,
    vae: Path | None = None,
    resume: bool = True,
    training: Annotated[FinetuneOptions, tyro.conf.OmitArgPrefixes] = FinetuneOptions(),  # noqa: B008
    model: Annotated[NVSModelOptions, tyro.conf.OmitArgPrefixes] = NVSModelOptions(),  # noqa: B008
) -> None:
    """Fine-tune the Free3D-style novel-view model on fixed-illumination multi-view sequences.

    Writes <out>/model (config.json + model.safetensors, EMA weights), checkpoints and train_log.jsonl.

    Args:
        out: run folder.
        data: OLAT data folders (default: the embedded fine-tuning objects).
        warp_hint: feed the reference forward-warped with its stored depth maps (default: on in pixel space;
            pixel space only).
        vae: local diffusers AutoencoderKL folder for latent space.
        resume: continue from the newest checkpoint in --out.
        training: fine-tuning settings (FinetuneConfig).
        model: the model's settings (NVSConfig; with --init-from, the init model's unless given).
    """
    from diamond_sss.data.embedded import embedded_dataset, finetune_object_names
    from diamond_sss.diffusion.nvs.train import finetune

    if data is None:
        data = [embedded_dataset(n) for n in finetune_object_names()]
    if not data:
        raise ValueError("no fine-tuning data: pass --data or install the embedded fine-tuning objects")
    config = config_from(FinetuneConfig, training, model=model_config(model, warp_hint, vae, training.init_from))
    console = Console()
    folder = finetune(data, out, config, resume=resume, log=console.print)
    console.print(f"model -> {folder}")


def model_config(options: NVSModelOptions, warp_hint: bool | None, vae: Path | None,
                 init_from: str | None) -> NVSConfig:
    """The architecture ``finetune-nvs`` trains: the defaults, or the ``init_from`` model's config, with the
    model options given on the command line (those not ``None``) on top."""
    from diamond_sss.diffusion.nvs.model import NVSModel

    given = {f.name: getattr(options, f.name) for f in dataclasses.fields(options) if getattr(options, f.name) is not None}
    if init_from is None:
        base = NVSConfig(vae_path=None, warp_hint=given.get("space", NVSConfig.space) == "pixel")
    else:
        base = NVSModel.read_config(init_from)
    if warp_hint is not None:
        given["warp_hint"] = warp_hint
    if vae is not None:
        given["vae_path"] = str(vae)
    return dataclasses.replace(base, **given)


def nvs(
    data: Path,
    view: int,
    light: int,
    targets: str,
    out: Path,
    split: str = "train",
    model: Path | None = None,
    steps: int = 1,
    guidance_scale: float = 1.0,
    seed: int = 0,
    cache: Path | None = None,
    device: str = "auto",
    geometry: str | None = None,
) -> None:
    """Generate novel views of an object under a fixed light from one reference image (Free3D-style model).

    Writes <out>/images/<name>.png (sRGB, premultiplied, with alpha), <out>/masks/<name>.png and
    <out>/manifest.json (a list of {view, light, image, mask}; view is null for a camera from a pose file); results
    are cached by model hash and input hash.

    Args:
        data: OLAT data folder holding transforms_<split>.json.
        view: reference view index (lattice index in the split).
        light: light index of the reference image (the generated views keep this light).
        targets: lattice view indices ("3,7,12") or a JSON file of 4x4 OpenGL camera-to-world matrices
            (a list, or {"camera_angle_x": f, "frames": [{"transform_matrix": M}]}).
        out: output folder.
        split: data split of the reference and of the target indices.
        model: model folder (config.json + model.safetensors); default: the model shipped in the package.
        steps: DDIM steps (the shipped model is best with 1: see benchmarks/RESULTS.md).
        guidance_scale: classifier-free guidance scale (1: no guidance).
        seed: seed of the shared initial noise.
        cache: cache folder (default $DIAMOND_SSS_CACHE/nvs or ~/.cache/diamond_sss/nvs).
        device: auto (CUDA when available, else CPU) | cpu | cuda[:i].
        geometry: metric depth of the reference for models with the warp hint: a reconstruction run folder
            (holding model.safetensors) or 'maps' (depth maps stored with the data).
    """
    from diamond_sss.data.dataset import OLATDataset
    from diamond_sss.diffusion.geometry import geometry_source
    from diamond_sss.diffusion.nvs.pipeline import generate_novel_views, parse_targets
    from diamond_sss.utils.device import resolve_device

    device = str(resolve_device(device))
    manifest = generate_novel_views(
        data,
        out,
        view,
        light,
        parse_targets(targets, OLATDataset(data, split)),
        split=split,
        model_dir=model,
        steps=steps,
        guidance_scale=guidance_scale,
        seed=seed,
        cache_dir=cache,
        device=device,
        geometry=None if geometry is None else geometry_source(geometry, device=device, seed=seed),
    )
    Console().print(f"novel views -> {manifest}")


def convert_free3d(src: Annotated[Path, tyro.conf.Positional, tyro.conf.arg(metavar="SRC")],
                   out: Annotated[Path, tyro.conf.Positional, tyro.conf.arg(metavar="OUT")], image_size: int = 256, vae: Path | None = None, seed: int = 0,
                   half: bool = False) -> None:
    """Convert the official Free3D checkpoint into a novel-view model folder (config.json + model.safetensors).

    The UNet (with ray conditioning and multi-view attention) and the context projection come from the
    checkpoint; Free3D embeds the reference with CLIP, which this model replaces by a small reference
    encoder: that encoder starts from a seeded initialisation and needs fine-tuning before the model
    conditions on the reference. The VAE is not converted: give the SD 1.x VAE as a diffusers folder.

    Args:
        src: official checkpoint (.ckpt with a state_dict, or .safetensors).
        out: model folder to write (for `nvs --model` and `run --nvs-model`).
        image_size: side of the generated images in pixels (Free3D: 256).
        vae: local diffusers AutoencoderKL folder recorded in config.json (latent space).
        seed: seed of the reference encoder's initialisation.
        half: store the weights in float16.
    """
    from diamond_sss.diffusion.nvs.convert import free3d_config

    config = free3d_config(image_size=image_size, vae_path=None if vae is None else str(vae))
    folder, count = write_free3d_model(src, out, config, seed=seed, half=half)
    Console().print(f"{count} tensors from {src} -> {folder} (use it with --model / --nvs-model)")


def write_free3d_model(src: Path, out: Path, config, seed: int = 0, half: bool = False) -> tuple[Path, int]:
    """Write the model folder of ``convert-free3d`` for ``config`` (an NVSConfig); returns it and the number
    of tensors taken from the checkpoint."""
    import pickle
    from dataclasses import asdict

    import torch

    from diamond_sss.diffusion.common.model_io import save_model
    from diamond_sss.diffusion.nvs.convert import load_free3d_checkpoint
    from diamond_sss.diffusion.nvs.model import MODEL_KIND, ReferenceEncoder

    try:
        converted, _ = load_free3d_checkpoint(src, config)
    except KeyError as exc:
        raise ValueError(f"{src}: not an official Free3D checkpoint ({exc.args[0]})") from exc
    except (pickle.UnpicklingError, RuntimeError, EOFError) as exc:
        raise ValueError(f"{src}: damaged or unreadable checkpoint ({exc})") from exc
    with torch.random.fork_rng():
        torch.manual_seed(seed)
        encoder = ReferenceEncoder(config.model_channels, config.encoder_channels, config.embed_dim)
    tensors = {**converted, **{f"reference_encoder.{k}": v for k, v in encoder.state_dict().items()},
               "null_embedding": torch.zeros(config.embed_dim)}
    save_model(out, MODEL_KIND, asdict(config), tensors, half=half)
    return Path(out), len(converted)
