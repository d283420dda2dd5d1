"""Settings of the DIAMOND-SSS pipeline besides the reconstruction's own (no torch: the CLI derives its options)."""

from __future__ import annotations

from dataclasses import dataclass

from diamond_sss.utils.fields import described

AUGMENTS = ("nvs", "relight", "repair")
"""The diffusion stages, in the order they run: the paper's two (``nvs``, ``relight``), or ``repair`` alone (issue
59, beyond the paper: the preliminary reconstruction's renders at the same targets, repaired by one model)."""

REPAIR_ROUNDS = 2
"""Default rounds of ``--augment repair``: on held-out objects at 9 images a second round (repairing the first
final reconstruction's renders) gained +1.10 / +0.40 dB on the deciding objects, +0.19 / +0.75 on the reporting
ones (session 44, ``benchmarks/RESULTS.md``). Over every two-round run since (session 50): +0.48 dB mean at 9 images
(12 runs), +0.10 at 30 (16; session 52), +0.01 on a rig framing the object at half the priors' scale (its knots,
16), and -0.23 on that rig's compact shapes (8), whose mask IoU it lowers by 0.03-0.05 as each round's generated
masks shrink (to 91-92% of the round before's area there, 95-99% on the first rig; the repair stage records and
prints the ratio, ``mask_area_vs_previous_round``): there one round is better, and ``MIN_ROUND_MASK_AREA`` stops the rounds."""

MIN_ROUND_MASK_AREA = 0.94
"""Default ``min_round_mask_area``. Over the 56 two-round repair runs of sessions 44-50 (three rigs, 9 and 30 images;
``benchmarks/results/ablation/pipeline_final_s51``) the ratio splits by rig: 0.903-0.934 on the rig that frames the
object at half the priors' scale (24 runs, round 2 - round 1 -0.07 dB mean, mask IoU -0.014), 0.946-0.993 on the
others (32 runs, +0.26 dB, IoU -0.002). Set before a fourth rig (object ~62% of the image width) was run: there the
ratio was 0.910-0.930 on all 15 runs; on the 9 that ran both rounds, round 2 changed the test PSNR by -0.31 dB on
average (lower on 8), the mask IoU by -0.030 (lower on all 9; session 51). Set with the shipped repair model: one
trained with pairs from two more rigs (``scripts/make_repair_rig_pairs.sh``) shrank the far rig's masks less (0.965 /
0.971) and the second round still lost 0.82 / 0.46 dB (session 52), so another model needs its own threshold."""

SHORT_RUN_PRELIM_PRESET = "sss3dgs"
"""Preset of a short run's preliminary reconstruction (``diamond-sss run --short-run``), as the demo and
``benchmarks/regimes.py`` train it: SSS-3DGS on the regime's real images, whose run is also their baseline row."""


@dataclass(frozen=True)
class PipelineConfig:
    """Settings of :func:`~diamond_sss.pipeline.run.run_pipeline` besides the reconstruction's configuration."""

    augment: tuple[str, ...] = described(AUGMENTS[:2], "diffusion stages to run: a subset of nvs, relight; or repair "
                                                       "alone")
    prelim_iterations: int | None = described(None, "training steps of the preliminary reconstruction, its "
                                                    "schedule scaled to them (default: its settings' steps)")
    prelim_preset: str | None = described(None, "preset of the preliminary reconstruction (default: the final "
                                                "one's; under `run`'s default preset auto or with --short-run, "
                                                "sss3dgs)")
    prelim_run: str | None = described(None, "a finished reconstruction of the same real images (a `train` run "
                                             "folder with this regime and seed) reused as the preliminary one")
    rounds: int | None = described(None, "rounds of the pipeline: each round after the first takes the previous "
                                         "round's final reconstruction (in <out>/round<k>) as its preliminary one "
                                         "and generates its images again from that geometry (default: 2 with "
                                         "--augment repair, measured on held-out objects; else 1)")
    min_round_mask_area: float = described(MIN_ROUND_MASK_AREA, "a round after the first whose repaired images' "
                                                               "masks cover less than this fraction of the previous "
                                                               "round's area (the same cameras and lights) trains "
                                                               "nothing: it keeps the previous round's final "
                                                               "reconstruction, and so do the rounds after it (0: "
                                                               "every round trains)")
    rig: str | None = described(None, "a light stage's full layout (a transforms file with top-level cameras and "
                                      "lights, no images) whose cameras and lights the diffusion stages target; "
                                      "default: the capture's own lattice when the regime leaves some of its cameras "
                                      "or lights out, else rig_views cameras and rig_lights lights placed around "
                                      "the real ones")
    rig_views: int = described(12, "cameras placed around the real ones when the capture has no lattice to "
                                    "generate on (only its sparse images) and no rig is given")
    rig_lights: int = described(8, "lights placed around the real ones when the capture has no lattice to "
                                   "generate on and no rig is given")
    rig_view_angle: float = described(0.0, "placed cameras lie within this angle (degrees) of the nearest real "
                                           "camera (0: anywhere in the real cameras' band)")
    rig_framing: str = described("auto", "how the placed cameras, and a lattice capture's cameras without an "
                                         "image, frame the object: prior (zoomed and centred so that it fills the "
                                         "image as in the priors' training images; the novel-view reference "
                                         "resampled to match), real (as the capture's cameras "
                                         "do; a --rig file's keep theirs), or auto: prior with --augment repair, "
                                         "real with the paper's stages or a --rig file (measured on a rig framed "
                                         "unlike the priors')")
    nvs_views: int = described(12, "at most this many missing views generated per real light (0: all)")
    relight_lights: int = described(8, "at most this many missing lights generated per view (0: all)")
    nvs_model: str | None = described(None, "folder of a novel-view model (default: the shipped one)")
    relight_model: str | None = described(None, "folder of a relighting model (default: the shipped one)")
    repair_model: str | None = described(None, "folder of a render-repair model (default: the shipped one; "
                                               "`diamond-sss repair-train` makes one)")
    nvs_geometry: str | None = described(None, "metric depth of the real views that the novel-view model's warp "
                                               "hint splats: a --geometry source with metric depth (maps: the "
                                               "capture's stored depth maps, e.g. a depth sensor's; or a "
                                               "reconstruction run folder); default: the preliminary "
                                               "reconstruction's render")
    nvs_canonical: bool = described(False, "give the novel-view prior the cameras in its own rig's frame (object "
                                           "at the origin, +Z up, cameras at its training distance) instead of "
                                           "the capture's")
    nvs_steps: int = described(1, "DDIM steps of the novel-view model (the shipped model is best with 1)")
    relight_steps: int = described(1, "DDIM steps of the relighting model (the shipped model is best with 1)")
    relight_samples: int = described(8, "relighting samples averaged per image (test-time ensemble)")
    nvs_guidance: float = described(1.0, "classifier-free guidance scale of the novel-view model (1: none)")
    min_silhouette_iou: float = described(0.8, "generated images whose mask has a lower IoU with the "
                                               "preliminary reconstruction's silhouette are dropped (0.8 measured "
                                               "on held-out objects: blurred novel views filled the knot's holes)")
    min_mask_fraction: float = described(0.002, "generated images whose mask covers a smaller fraction of the "
                                                "image are dropped")
    synthetic_weight: float = described(0.5, "photometric loss weight of a generated image in the final "
                                             "reconstruction, relative to a real image's 1 (absolute, not "
                                             "normalised in the batch)")
    agreement_power: float = described(0.0, "generated images whose sRGB error against the preliminary "
                                            "reconstruction's render exceeds the median error have their weight "
                                            "multiplied by (median / error)^power (0: every image at alpha)")
    min_real_share: float | None = described(None, "the real images are repeated in the final reconstruction's "
                                                   "training set until they make up at least this share of the "
                                                   "images drawn (0: each image once, as the paper; default: "
                                                   "n / (n + generated_as_real) for n real images)")
    generated_as_real: float = described(9.0, "without min_real_share, the generated images together are drawn "
                                              "about as often as this many real images: a real share of 0.5 at 9 "
                                              "real images, 0.77 at 30")
    cache_dir: str | None = described(None, "cache of generated images (default: ~/.cache/diamond_sss or "
                                            "$DIAMOND_SSS_CACHE)")
    generation_threads: int | None = described(None, "torch CPU threads of the generation stages (novel views, "
                                                      "relighting, repair) on a CPU: default the cores other "
                                                      "processes leave idle when the stage starts (at least 1); 0: "
                                                      "torch's default (every core)")
    device: str = described("auto", "auto (CUDA when available, else CPU) | cpu | cuda[:i] for the diffusion models "
                                    "(reconstructions use --set device=...)")
