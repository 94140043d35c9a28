"""How the pose pipeline runs: one typed configuration, its defaults written here once.

:class:`InferenceConfig` is read by :class:`~cosy_lite.inference.predictor.Predictor`, written into a
reference set's ``pipeline.json`` (key ``inference``) and into an export's ``manifest.json``, and
built by ``cosy-lite infer`` / ``predict`` from, in order (later wins): these defaults, the
reference set's or the export's settings, ``--settings FILE`` (YAML or JSON), the command's flags
(``--start``, ``--candidates`` ...) and ``--set KEY=VALUE`` overrides. Every problem is a
:class:`~cosy_lite.errors.ConfigError` naming the file (or flag) and the field.

No torch here: the command-line parsers read it.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Mapping, Sequence

from cosy_lite.errors import FieldValueError
from cosy_lite.inference.icp import IcpConfig
from cosy_lite.inference.starts import STARTS, TEMPLATE_STARTS
from cosy_lite.nets.detection_masks import MASK_THRESHOLD

CANDIDATE_CHOICES = ("confidence", "start")
PRECISIONS = ("fp32", "bf16", "int8")  # bf16: torch autocast; int8: the quantised ONNX pose networks
# predict's defaults under every other layer: a person reads each estimate, so wrong ones cost. Measured
# (python bench/bench_score_threshold.py, the demo detector's 2,417 detections of the 100 test images): the
# best F1 of the kept detections, 0.635 (precision 0.77, recall 0.54, 5.7 per image against 24.2 unfiltered
# with precision 0.25). infer keeps InferenceConfig's (no filter): BOP19 AR counts no false positive.
PREDICT_DEFAULTS: dict[str, Any] = {"min_score": 0.5, "max_per_object": 1}
# --exact-masks: the settings for detections whose masks are exact (GT, or checked by hand), chosen on a second
# generated split of 100 images (GT masks RGB AR 0.4177 -> 0.4521; margins 0.03 / 0.05 / 0.1: 0.4519 / 0.4521 /
# 0.4486) and measured on the test split (0.4225 -> 0.4520). The detector's masks lose with them (0.2883 -> 0.2559).
EXACT_MASK_SETTINGS = ("silhouette_guard=0.05", "depth_from_mask=true")


@dataclass
class InferenceConfig:
    """Everything that decides the poses of an image, apart from the networks and the objects."""

    start: str = "coarse"  # a key of STARTS (cosy_lite.inference.starts)
    n_candidates: int = 1  # template starts: the best templates; candidate_choice says which goes on
    # which of several candidates goes on: "confidence" (the refiner's, after its one iteration) or "start"
    # (the start stage's best: the RGB poses and time of one candidate; the others go only to ICP, as hypotheses)
    candidate_choice: str = "confidence"
    n_refiner_iterations: int = 4  # after the start (CosyPose: trained with 1, run with 4)
    # The refiner's own depth bias: its median depth / GT depth after 1, 2, ... iterations started AT the GT
    # poses of training images (``cosy-lite score-refiner --from-gt --split train_pbr``, "depth_ratio_median").
    # The refined depth is divided by the entry of the iterations run that set the depth (depth_iterations: the
    # fine ones keep it; the last entry beyond); empty: none.
    refiner_depth_drift: list[float] = field(default_factory=list)
    # Refiner iterations (1-based) run on larger crops, [h, w] px (multiples of 16), keeping their input's
    # depth: finer rotation and image position from a network trained on smaller crops, whose depth comes
    # out biased on them (cosy_lite.nets.render_and_compare.FineCrops). No iterations: every iteration at the
    # network's own crop size. (The candidates' choice iteration is never a fine one.)
    refiner_fine_iterations: list[int] = field(default_factory=list)
    refiner_fine_resolution: list[int] = field(default_factory=list)
    # For exact masks (GT or hand-checked) only; the detector's masks are not exact enough for either
    # (cosy_lite.inference.mask_fit; RGB AR of the 100 test images, GT masks / detector: 0.4225 / 0.2883 without,
    # 0.4423 / 0.2652 with depth_from_mask, 0.4520 with both).
    # The refiner's last iteration kept unless its silhouette's IoU with the mask is under an earlier one's by
    # more than this margin (then that one); 0: off.
    silhouette_guard: float = 0.0
    # After the refiner, the depth whose rendered silhouette best covers the detection's mask.
    depth_from_mask: bool = False
    # The detector's masks: its mask head's probabilities above this (torchvision: 0.5). They set the start
    # stage's silhouettes and appearance crops and the ICP windows (cosy_lite.nets.detection_masks). A set's
    # pipeline.json chooses its detector's: ycbvsynth 0.275 (larger masks; chosen on a second generated split:
    # RGB / + ICP AR 0.2885 / 0.4916 at 0.5, 0.2944 / 0.5269 at 0.275; mask AP 0.351 -> 0.337: bench/RESULTS.md).
    mask_threshold: float = MASK_THRESHOLD
    min_score: float = 0.0  # pose only detections scoring at least this (BOP19: any threshold lowers AR)
    one_per_region: bool = False  # at most one detection per image region (mask IoU > 0.5, any class)
    max_per_object: int = 0  # at most this many detections per object and image, the best scored (0: no limit)
    # BOP19 ViVo (Predictor.predict with inst_counts: cosy-lite infer's 6d-localization): pose up to this many
    # detections per target instance, the best scored of its object that score at least vivo_score_ratio x its best,
    # and keep the inst_count the refiner is most confident of (cosy_lite.inference.vivo): in its last iteration on its
    # own crop size, before the iterations on larger crops (refiner_fine_iterations), which only those run; only those
    # go on to ICP. 1: the inst_count best scored. The ycbvsynth set: 2 (for 7 % of the targets the detector's
    # best is wrong and another right; chosen on a second generated split, bench/RESULTS.md, session 31).
    vivo_candidates: int = 1
    vivo_score_ratio: float = 0.3
    icp: bool = False  # refine with the depth image (point-to-plane ICP) when one is given
    icp_settings: IcpConfig = field(default_factory=IcpConfig)
    precision: str = "fp32"  # a key of PRECISIONS
    batch_size: int = 32  # crops per network call
    channels_last: bool = True  # torch networks in channels-last memory (same numbers, faster on CPU)
    fuse_bn: bool = True  # BatchNorm folded into the convolutions (torch: the pose networks and the coarse scorer)

    def __post_init__(self) -> None:
        checks = (("start", self.start in STARTS, f"one of {list(STARTS)}"),
                  ("n_candidates", self.n_candidates >= 1, "an integer >= 1"),
                  ("candidate_choice", self.candidate_choice in CANDIDATE_CHOICES, f"one of {list(CANDIDATE_CHOICES)}"),
                  ("n_refiner_iterations", self.n_refiner_iterations >= 0, "an integer >= 0"),
                  ("mask_threshold", 0.0 < self.mask_threshold < 1.0, "a mask probability in (0, 1)"),
                  ("min_score", 0.0 <= self.min_score <= 1.0, "a score in [0, 1]"),
                  ("max_per_object", self.max_per_object >= 0, "an integer >= 0 (0: no limit)"),
                  ("vivo_candidates", self.vivo_candidates >= 1, "an integer >= 1 (1: the best scored)"),
                  ("vivo_score_ratio", 0.0 <= self.vivo_score_ratio <= 1.0, "a share of the best score in [0, 1]"),
                  ("precision", self.precision in PRECISIONS, f"one of {list(PRECISIONS)}"),
                  ("batch_size", self.batch_size >= 1, "an integer >= 1"),
                  ("silhouette_guard", 0.0 <= self.silhouette_guard < 1.0, "an IoU margin in [0, 1) (0: off)"))
        for name, ok, expected in checks:
            if not ok:
                raise FieldValueError(name, f"{getattr(self, name)!r}: expected {expected}")
        if not all(isinstance(r, (int, float)) and 0.5 <= r <= 2.0 for r in self.refiner_depth_drift):
            raise FieldValueError("refiner_depth_drift", f"{self.refiner_depth_drift!r}: expected depth ratios in "
                                  "[0.5, 2] (the refiner's median depth / GT depth per iteration, e.g. [1.006, 1.01])")
        if not all(isinstance(i, int) and not isinstance(i, bool) and i >= 1 for i in self.refiner_fine_iterations):
            raise FieldValueError("refiner_fine_iterations", f"{self.refiner_fine_iterations!r}: expected iteration "
                                  "numbers >= 1 (e.g. [2, 4])")
        res = self.refiner_fine_resolution
        if res and not (len(res) == 2 and all(isinstance(v, int) and not isinstance(v, bool) and v >= 16 and v % 16 == 0
                                              for v in res)):
            raise FieldValueError("refiner_fine_resolution", f"{res!r}: expected [h, w] px, multiples of 16 (e.g. [240, 320])")
        if self.refiner_fine_iterations and not res:
            raise FieldValueError("refiner_fine_resolution", f"refiner_fine_iterations {self.refiner_fine_iterations!r} "
                                  "needs a crop size, e.g. [240, 320]")
        if self.n_candidates > 1 and self.start not in TEMPLATE_STARTS:
            raise FieldValueError("n_candidates", f"{self.n_candidates} needs a template start ({list(TEMPLATE_STARTS)}), "
                             f"not start = {self.start!r}")
        if self.n_candidates > 1 and self.n_refiner_iterations < 1:
            raise FieldValueError("n_candidates", f"{self.n_candidates} needs n_refiner_iterations >= 1: the refiner's "
                             "confidence after one iteration ranks the candidates")

    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)

    def depth_iterations(self, through: int | None = None) -> int:
        """The refiner iterations run (up to iteration ``through``; None: all) that set the depth: those not
        among :attr:`refiner_fine_iterations` (a fine iteration keeps its input's depth, so it adds no drift)."""
        n = self.n_refiner_iterations if through is None else min(through, self.n_refiner_iterations)
        return n - len({i for i in self.refiner_fine_iterations if i <= n})

    def depth_drift(self, n_iterations: int) -> float:
        """The refiner's depth ratio after ``n_iterations`` (:attr:`refiner_depth_drift`; 1.0: none)."""
        drift = self.refiner_depth_drift
        return float(drift[min(n_iterations, len(drift)) - 1]) if drift and n_iterations >= 1 else 1.0


def inference_config(base: Mapping[str, Any] | None = None, base_source: str | Path = "",
                     settings_file: str | Path | None = None, overrides: Sequence[str] = ()) -> InferenceConfig:
    """The defaults <- ``base`` (settings read from ``base_source``, e.g. the ``inference`` of a
    ``pipeline.json``) <- ``settings_file`` (YAML/JSON) <- ``overrides`` ("key=value"). Raises
    ConfigError naming the source and the field."""
    from cosy_lite.config import load_config

    layers = [] if base is None else [(str(base_source or "settings"), base)]
    return load_config(InferenceConfig, settings_file, list(overrides), layers=layers)


def with_refiner(config: InferenceConfig, has_refiner: bool) -> InferenceConfig:
    """``config`` for a pipeline without a refiner network: no refiner iterations, one candidate."""
    if has_refiner:
        return config
    return dataclasses.replace(config, n_refiner_iterations=0, n_candidates=1)


# --------------------------------------------------------------------------- command lines
def add_arguments(ap: Any, what: str = "") -> None:
    """The inference flags shared by ``infer`` and ``predict`` (defaults: None, i.e. the settings'
    value; :func:`config_from_arguments` resolves them)."""
    ap.add_argument("--settings", type=Path, default=None, metavar="FILE",
                    help="inference settings, YAML or JSON (cosy_lite.inference.settings.InferenceConfig); default: the "
                         "--pretrained set's or the export's, else the defaults")
    ap.add_argument("--set", nargs="+", default=[], metavar="KEY=VALUE", dest="set_overrides",
                    help="change settings, e.g. n_refiner_iterations=2 icp_settings.max_translation=0.1 batch_size=8")
    ap.add_argument("--start", default=None, choices=STARTS,
                    help="start poses: coarse (box pose -> the coarse network, CosyPose), templates (the detection "
                         "mask matched against rendered silhouettes) or appearance (those templates ranked by the "
                         "image inside the mask as well)")
    ap.add_argument("--candidates", type=int, default=None, metavar="K",
                    help="template starts: the K best templates each get one refiner iteration; the most confident "
                         "goes on, or with candidate_choice=start the start stage's best (K > 1 needs a flow refiner)")
    ap.add_argument("--n-refiner-iters", type=int, default=None, metavar="N", help="refiner iterations")
    ap.add_argument("--min-score", type=float, default=None, metavar="S",
                    help="pose only detections scoring at least S (BOP19: any threshold only lowers AR, "
                         "bench/RESULTS.md 'Detection threshold')")
    ap.add_argument("--max-per-object", type=int, default=None, metavar="K",
                    help="pose at most K detections per object and image, the best scored (0: no limit)")
    ap.add_argument("--one-per-region", action="store_true", default=None,
                    help="at most one detection per image region (mask IoU > 0.5, any class; the best scored)")
    ap.add_argument("--exact-masks", action="store_true", default=None,
                    help="the given detections' masks are exact (GT, or checked by hand): the refined poses are checked "
                         f"and their depth fitted against them ({' '.join(EXACT_MASK_SETTINGS)}; --set wins). Not for "
                         "a detector's masks, whose edges are not exact enough")
    ap.add_argument("--icp", action="store_true", default=None, help=f"refine with the depth {what}(point-to-plane ICP)")
    ap.add_argument("--icp-set", nargs="+", default=[], metavar="KEY=VALUE",
                    help="ICP settings (cosy_lite.inference.icp.IcpConfig), e.g. max_translation=0.1 or "
                         "verify_candidates=false; the same as --set icp_settings.KEY=VALUE")
    ap.add_argument("--precision", default=None, choices=PRECISIONS,
                    help="pose networks' arithmetic: fp32; bf16 autocast (torch, faster on CPUs with AVX512-BF16); "
                         "int8 (onnx, exported with --quantize int8)")


# flag (namespace attribute) -> InferenceConfig key
FLAG_KEYS = {"start": "start", "candidates": "n_candidates", "n_refiner_iters": "n_refiner_iterations",
             "min_score": "min_score", "max_per_object": "max_per_object", "one_per_region": "one_per_region",
             "icp": "icp", "precision": "precision"}


def flag_problem(args: Any) -> str | None:
    """What is wrong with a settings flag's value alone, named as the user typed it (None: nothing;
    the settings themselves check every field again, :class:`InferenceConfig`)."""
    for attr, key in FLAG_KEYS.items():
        value = getattr(args, attr, None)
        if value is None:
            continue
        try:
            InferenceConfig(**{key: value, **({"start": "templates"} if key == "n_candidates" else {})})
        except FieldValueError as e:
            return f"--{attr.replace('_', '-')} {value}: {e.problem.split(': ', 1)[-1]}"
    if getattr(args, "exact_masks", None) and getattr(args, "detections", None) is None:
        return ("--exact-masks: the detector's masks are not exact (it lowers their AR); give --detections with exact "
                "masks (infer: oracle or a file)")
    return None


def config_from_arguments(args: Any, base: Mapping[str, Any] | None = None,
                          base_source: str | Path = "") -> InferenceConfig:
    """The settings of a command line (:func:`add_arguments`) on top of ``base`` (the settings of a
    reference set's ``pipeline.json`` or an export's manifest, read from ``base_source``). A
    ``--start`` other than the base's resets the candidates to 1 unless ``--candidates`` is given:
    a set's candidate count belongs to its own start; so does ``--n-refiner-iters 0`` (no refiner
    iteration ranks candidates)."""
    flags = [f"{key}={getattr(args, attr)}" for attr, key in FLAG_KEYS.items() if getattr(args, attr, None) is not None]
    if (base and getattr(args, "candidates", None) is None and getattr(args, "start", None) is not None
            and args.start != base.get("start", InferenceConfig.start)):
        flags.append("n_candidates=1")
    if getattr(args, "n_refiner_iters", None) == 0 and getattr(args, "candidates", None) is None:
        flags.append("n_candidates=1")  # no refiner iteration ranks candidates: the best template is the start
    if getattr(args, "exact_masks", None):
        flags += EXACT_MASK_SETTINGS
    overrides = [*flags, *(f"icp_settings.{kv}" for kv in getattr(args, "icp_set", [])),
                 *getattr(args, "set_overrides", [])]
    return inference_config(base, base_source, getattr(args, "settings", None), overrides)


def templates_cache(args: Any) -> Path:
    """``--templates-cache DIR``, else ``$COSY_LITE_CACHE/templates``: templates are rendered once per
    object and mesh (a warm ``predict`` re-rendered them all: 187 s instead of seconds)."""
    from cosy_lite.bop.folders import default_cache_dir

    given = getattr(args, "templates_cache", None)
    return Path(given) if given is not None else default_cache_dir() / "templates"


def pretrained_config(args: Any, use_networks: bool = True, defaults: Mapping[str, Any] | None = None) -> InferenceConfig:
    """:func:`config_from_arguments` over the settings of ``--pretrained NAME`` (``args.pretrained``;
    none: the defaults), and the set's networks filled in where ``args`` leaves them None: the
    detector and refiner, the coarse network when the poses start from it, the scorer when they start
    from the appearance templates (``use_networks`` False: the set is not used, for a backend that
    does not take its networks). Raises ReferenceModelError for an unknown name, ConfigError naming
    ``pipeline.json`` or the flag and the field for a bad setting."""
    from cosy_lite.weights.reference_models import KINDS, fill_networks, reference_models

    if getattr(args, "pretrained", None) is None or not use_networks:
        return config_from_arguments(args, defaults, "the command's defaults")
    ref = reference_models(args.pretrained)
    config = config_from_arguments(args, {**(defaults or {}), **ref.inference}, ref.pipeline_path)
    unused = {"coarse": config.start != "coarse", "scorer": config.start != "appearance"}
    fill_networks(args, ref, tuple(k for k in KINDS if not unused.get(k, False)))
    return config
