"""The pose-estimation pipeline for one RGB(-D) image: detector -> coarse -> refiner -> depth ICP.

Per image: the image is converted to a tensor once; every detected object goes through the
networks together (one batch per iteration, see :func:`~cosy_lite.nets.render_and_compare.iterate_poses`,
all crops of an iteration rendered in one call). Starting pose (``start``):

* ``"coarse"`` (CosyPose): canonical rotation and depth from the detection box
  (:func:`~cosy_lite.nets.initial_pose.initial_pose_from_boxes`) -> 1 coarse iteration;
* ``"templates"``: the detection mask matched against rendered silhouettes
  (:class:`~cosy_lite.nets.silhouette_templates.SilhouetteTemplates`, no network);
  ``"appearance"``: the same templates ranked by the image inside the mask against textured
  renderings as well (:class:`~cosy_lite.nets.appearance_templates.AppearanceTemplates`); with
  ``n_candidates`` > 1 the best templates each get one refiner iteration and the one the flow
  refiner is most confident about (:func:`~cosy_lite.nets.render_and_compare.refine_and_score`)
  goes on (that iteration counts as the first of ``n_refiner_iterations``), or with
  ``candidate_choice="start"`` the start stage's best (the others go, as the start stage made them,
  only to ICP as hypotheses);

-> ``n_refiner_iterations`` refiner iterations (CosyPose: 1 + 4) -> optionally point-to-plane ICP
against the measured depth inside each detection mask (:func:`~cosy_lite.inference.icp.refine_poses_icp`).

Robot users: ``Predictor.from_checkpoints(coarse=..., refiner=..., models_dir=...)`` then
``predict(rgb, K)``; no dataset needed, only the BOP ``models/`` folder of the objects (PLY in mm
+ ``models_info.json``). Poses are object-to-camera in metres. Exported networks (``cosy-lite
export``): ``Predictor.from_onnx(export_dir, models_dir=...)`` runs the same pipeline with the
networks (detector, coarse network or coarse scorer, refiner) in onnxruntime and everything around
them (crops, renders, pose updates, ICP) in the one render-and-compare loop of the torch pipeline.
"""

from __future__ import annotations

import dataclasses
import time
import warnings
from pathlib import Path
from typing import TYPE_CHECKING, Any, Callable, Mapping, Sequence, TypeAlias

import numpy as np
import torch
from torch import Tensor, nn

from cosy_lite.bop.detections import MIN_BOX_SIZE_PX, Detections, degenerate_boxes, describe_boxes
from cosy_lite.geometry.pose_checks import orthonormalise, valid_poses
from cosy_lite.inference.depth_refinement import DepthRefinement, box_masks
from cosy_lite.inference.detection_filter import DetectionFilter
from cosy_lite.inference.mask_fit import fit_depth_to_masks, guarded_iterations
from cosy_lite.inference.object_meshes import (
    SetupError,
    estimated_obj_ids,
    object_meshes,
    objects_and_renderer,
    render_shading,
    start_templates,
)
from cosy_lite.inference.pose_estimates import TIMING_KEYS, PoseEstimates
from cosy_lite.inference.settings import InferenceConfig, inference_config, with_refiner
from cosy_lite.inference.starts import STARTS, TEMPLATE_STARTS
from cosy_lite.inference.torch_runtime import AUTOCAST_DTYPES, Clock, TimedRenderer, flush_denormals, inference_net, timed_net
from cosy_lite.inference.vivo import most_confident, select_candidates
from cosy_lite.nets.appearance_templates import CROP_SIZE, AppearanceTemplates

# torchvision at import, before any rendering: importing it (-> triton's LLVM) after Mesa's llvmpipe
# has rendered crashes the process.
from cosy_lite.nets.detector import detect
from cosy_lite.nets.initial_pose import initial_pose_from_boxes
from cosy_lite.nets.render_and_compare import FineCrops, iterate_poses_scored, refine_and_score
from cosy_lite.nets.silhouette_templates import SilhouetteTemplates
from cosy_lite.weights.loaders import PoseModel, load_detector, load_pose_model

if TYPE_CHECKING:
    from cosy_lite.bop.dataset import BopDataset
    from cosy_lite.inference.onnx_runtime import OnnxDetector
    from cosy_lite.nets.detector import Detector
    from cosy_lite.nets.object_table import ObjectTable
    from cosy_lite.render.renderer import MeshRenderer, Renderer

# what the factories take as ``dataset``: a dataset or its folder (its ``models/`` is read)
DatasetSource: TypeAlias = "BopDataset | str | Path | None"

__all__ = ["Predictor", "PoseEstimates", "SetupError", "STARTS", "TIMING_KEYS"]



def _as_rgb(rgb: Any) -> np.ndarray:
    rgb = np.asarray(rgb)
    if rgb.ndim != 3 or rgb.shape[2] != 3 or rgb.dtype != np.uint8:
        raise ValueError(f"rgb must be [H,W,3] uint8, got {rgb.dtype} {rgb.shape}")
    return rgb


def _as_K(K: Any) -> Tensor:
    K = torch.as_tensor(np.asarray(K, dtype=np.float64))
    if K.shape != (3, 3) or not torch.isfinite(K).all() or K[0, 0] <= 0 or K[1, 1] <= 0:
        raise ValueError(f"K must be a finite [3,3] with fx, fy > 0, got {tuple(K.shape)}")
    return K


def _load_scorer(path: str | Path, start: str, obj_ids: Sequence[int], renderer: MeshRenderer,
                 fuse_bn: bool = True) -> nn.Module:
    """The coarse scorer network of ``path``, checked against the pipeline it joins, as
    :func:`~cosy_lite.inference.torch_runtime.inference_net` makes it (BatchNorm folded if ``fuse_bn``)."""
    from cosy_lite.weights.loaders import load_scorer

    if start != "appearance":
        raise SetupError(f"{path}: a coarse scorer ranks the templates of start='appearance', not start={start!r}")
    scorer = load_scorer(path)
    _check_scorer(path, scorer.obj_ids, scorer.shading, obj_ids, renderer)
    return inference_net(scorer.net, torch.device("cpu"), True, fuse_bn, (2, 3, CROP_SIZE, CROP_SIZE))


def _check_scorer(path: str | Path, known: Sequence[int], shading: str, obj_ids: Sequence[int],
                  renderer: MeshRenderer) -> None:
    """SetupError naming the scorer file ``path`` unless it was trained on all ``obj_ids`` (it
    ``known`` ones) against templates rendered with the ``shading`` ``renderer`` renders with."""
    if missing := sorted(set(obj_ids) - set(known)):
        raise SetupError(f"{path}: the scorer was not trained on obj_ids {missing} (it knows {list(known)})")
    rendered = getattr(renderer, "shading", None)
    if rendered != shading:
        raise SetupError(f"{path}: the scorer was trained against templates rendered with {shading!r} shading, "
                         f"but this pipeline renders with {rendered!r} (the refiner's render_shading)")


Choice: TypeAlias = Callable[[Tensor | None], Tensor]  # the refiner's confidence [N] (None: none ran) -> kept indices


def _most_confident_of(det: Detections, inst_counts: Mapping[int, int]) -> Choice:
    """The choice of :func:`~cosy_lite.inference.vivo.most_confident` among ``det`` (the detection scores
    when no refiner iteration ran)."""
    counts = dict(inst_counts)

    def choose(confidence: Tensor | None) -> Tensor:
        return most_confident(det.obj_ids, det.scores if confidence is None else confidence, counts)

    return choose


def _split_before_fine(first: int, n_iterations: int, fine: FineCrops | None) -> list[tuple[int, int]]:
    """(first iteration, count) of the runs of ``n_iterations`` from ``first``: one, or with ``fine`` two when
    the last iterations run on larger crops after at least one on the network's own: those apart."""
    last = first + n_iterations - 1
    start_fine = last + 1
    while fine is not None and start_fine - 1 >= first and start_fine - 1 in fine.iterations:
        start_fine -= 1
    if not first < start_fine <= last:
        return [(first, n_iterations)] if n_iterations else []
    return [(first, start_fine - first), (start_fine, last - start_fine + 1)]


def check_fine_crops(config: InferenceConfig, refiner: PoseModel | None) -> None:
    """SetupError naming the file when ``refiner_fine_iterations`` ask for crops the refiner cannot take:
    larger crops need a network of any input size, a flow refiner (torch) or its graph exported so
    (onnxruntime: symbolic height and width, ``OnnxPoseNet.any_size``)."""
    if (config.refiner_fine_iterations and refiner is not None
            and not (refiner.output == "flow" and getattr(refiner.net, "any_size", True))):
        raise SetupError(f"{refiner.path or 'the refiner'}: refiner_fine_iterations {config.refiner_fine_iterations} "
                         f"run it on {config.refiner_fine_resolution} crops, but it takes only its own "
                         f"{list(refiner.crop_resolution)} (a regression refiner, or an ONNX graph exported before "
                         "2026-12-06: export it again); or --set refiner_fine_iterations=[]")


class Predictor:
    """Detector -> coarse -> refiner -> optional depth ICP, for single images.

    Args:
        coarse, refiner: the pose networks (:class:`~cosy_lite.weights.loaders.PoseModel`; torch
            modules, or onnxruntime sessions from :meth:`from_onnx`); refiner None: coarse only;
            coarse None: only with a template start (the coarse network is not used there).
        objects: :class:`~cosy_lite.nets.object_table.ObjectTable` of the objects to estimate
            (model points for the crops, diameters for the starting depth).
        renderer: batched renderer of the same objects (:class:`~cosy_lite.render.renderer.GlRenderer`).
        detector: :class:`~cosy_lite.nets.detector.Detector`, an
            :class:`~cosy_lite.inference.onnx_runtime.OnnxDetector`, or None (detections then have to be given).
        config: how the pipeline runs (:class:`~cosy_lite.inference.settings.InferenceConfig`: start,
            candidates, refiner iterations, detection filter, ICP, precision, batch size ...; None: its
            defaults). ``channels_last`` and ``fuse_bn`` act on copies of the torch networks
            (:func:`inference_net`); the given modules are not changed.
        icp_symmetries: obj_id -> symmetry set [S,4,4] (m) for ICP (None: no symmetry handling).
        device: where the networks run.
        templates: the :class:`~cosy_lite.nets.silhouette_templates.SilhouetteTemplates` to match
            (None: 2,048 per object, rendered with ``renderer`` on first use of each object).
    """

    def __init__(self, coarse: PoseModel | None, refiner: PoseModel | None, objects: ObjectTable, renderer: MeshRenderer,
                 detector: Detector | OnnxDetector | None = None, config: InferenceConfig | None = None,
                 icp_symmetries: dict[int, np.ndarray] | None = None, device: str | torch.device = "cpu",
                 templates: SilhouetteTemplates | None = None):
        config = config or InferenceConfig()
        if coarse is None and config.start == "coarse":
            raise SetupError("start='coarse' needs a coarse model (or use start='templates')")
        if config.n_candidates > 1 and (refiner is None or refiner.output != "flow"):
            raise SetupError(f"n_candidates = {config.n_candidates} needs a flow refiner (net.arch=flow): its "
                             "confidence ranks the candidates")
        check_fine_crops(config, refiner)
        if refiner is None and config.n_refiner_iterations > 0:
            raise ValueError(f"n_refiner_iterations = {config.n_refiner_iterations} but no refiner model given")
        if config.precision not in AUTOCAST_DTYPES:
            raise ValueError(f"precision must be one of {sorted(AUTOCAST_DTYPES)} here, got {config.precision!r}")
        self.config = config
        self.device = torch.device(device)
        self.coarse, self.refiner, self.detector = coarse, refiner, detector
        self.objects = objects.to(self.device)
        self.renderer = renderer
        self.depth_refinement = DepthRefinement(renderer, config.icp_settings, icp_symmetries)
        if config.start in TEMPLATE_STARTS and templates is None:
            templates = SilhouetteTemplates(renderer, self.objects.obj_ids,
                                            self.objects.diameters.detach().cpu().double().tolist())
        if config.start == "appearance" and templates is not None and templates.appearance is None:
            AppearanceTemplates(templates, renderer)  # attaches itself: templates.match ranks by appearance
        self.templates = templates
        self.detection_filter = DetectionFilter(config.min_score, config.one_per_region, max_per_object=config.max_per_object)
        if isinstance(detector, nn.Module):  # else an onnxruntime detector (OnnxDetector)
            detector.to(self.device).eval()
        self._nets: dict[str, nn.Module | Callable[[Tensor], Tensor]] = {}
        for role, m in (("coarse", coarse), ("refiner", refiner)):
            if m is not None:
                self._nets[role] = (inference_net(m.net, self.device, config.channels_last, config.fuse_bn,
                                                  (2, 6, *m.crop_resolution)) if isinstance(m.net, nn.Module) else m.net)
                missing = sorted(set(self.objects.obj_ids) - set(m.obj_ids))
                if missing:
                    raise SetupError(f"{m.describe()}: the {m.kind} model was not trained on obj_ids {missing} "
                                     f"(it knows {m.obj_ids})")

    @property
    def start(self) -> str:
        return self.config.start

    @property
    def n_candidates(self) -> int:
        return self.config.n_candidates

    @property
    def n_refiner_iterations(self) -> int:
        return self.config.n_refiner_iterations

    # ------------------------------------------------------------------ construction
    @classmethod
    def from_checkpoints(
        cls, detector: str | Path | None = None, coarse: str | Path | None = None,
        refiner: str | Path | None = None, models_dir: str | Path | None = None, dataset: DatasetSource = None,
        config: InferenceConfig | None = None, device: str | torch.device = "cpu",
        obj_ids: Sequence[int] | None = None, n_points: int | None = None,
        templates_cache: str | Path | None = None, scorer: str | Path | None = None,
    ) -> "Predictor":
        """Load the checkpoints and the object models.

        Args:
            detector, coarse, refiner: checkpoint files (``train.py`` outputs); detector None:
                detections are passed to :meth:`predict`; refiner None: coarse only.
            models_dir: a BOP ``models/`` folder, or ``dataset``: a
                :class:`~cosy_lite.bop.dataset.BopDataset` or dataset folder (its ``models/``).
            config: as the class (None: the defaults; without a refiner, no refiner iterations).
            obj_ids: objects to estimate (default: those of the coarse checkpoint).
            n_points: model points per object for the crop boxes (default: ObjectTable's).
            templates_cache: a folder where the rendered templates are kept between runs (None:
                rendered in every run).
            scorer: a coarse scorer file (``train.py --model scorer``) that describes the detections
                of ``start="appearance"`` (None: the frozen ImageNet features on both sides).
        Raises CheckpointError naming the file (missing, wrong kind, unreadable), SetupError when
        a checkpoint does not cover the objects.
        """
        config = with_refiner(config or InferenceConfig(), refiner is not None)
        if coarse is None and (config.start not in TEMPLATE_STARTS or refiner is None):
            raise SetupError("a coarse checkpoint is needed (coarse=...), or start='templates' with a refiner")
        meshes = object_meshes(models_dir, dataset)
        coarse_model = None if coarse is None else load_pose_model(coarse, "coarse", device)
        refiner_model = None if refiner is None else load_pose_model(refiner, "refiner", device)
        first = coarse_model or refiner_model
        ids = estimated_obj_ids(obj_ids, first.obj_ids, meshes.obj_ids,  # type: ignore[union-attr]
                                meshes.models_dir / "models_info.json")
        objects, renderer, syms = objects_and_renderer(meshes, ids, n_points, config.icp,
                                                    render_shading(coarse_model, refiner_model))
        det = None if detector is None else load_detector(detector, device)
        scorer_net = None if scorer is None else _load_scorer(scorer, config.start, ids, renderer, config.fuse_bn)
        templates = start_templates(config.start, meshes, objects, renderer, templates_cache, scorer_net)
        return cls(coarse_model, refiner_model, objects, renderer, det, config, syms, device, templates)

    @classmethod
    def from_pretrained(
        cls, name: str, models_dir: str | Path | None = None, dataset: DatasetSource = None, detector: bool = True,
        config: InferenceConfig | None = None, device: str | torch.device = "cpu",
        obj_ids: Sequence[int] | None = None, templates_cache: str | Path | None = None,
    ) -> "Predictor":
        """The shipped reference models ``name`` (:mod:`cosy_lite.weights.reference_models`, e.g.
        ``"ycbvsynth"``) run as the set's ``pipeline.json`` says (``config`` None; to change some of
        its settings: ``inference_config(reference_models(name).inference, overrides=["icp=true"])``).

        detector: use the set's detector (False: detections are passed to :meth:`predict`); the
        other arguments as :meth:`from_checkpoints`. Raises ReferenceModelError for an unknown name.
        """
        from cosy_lite.weights.reference_models import reference_models

        ref = reference_models(name)
        config = config or inference_config(ref.inference, ref.pipeline_path)
        return cls.from_checkpoints(
            detector=ref.path("detector") if detector else None,
            coarse=ref.path("coarse") if config.start == "coarse" else None, refiner=ref.path("refiner"),
            models_dir=models_dir, dataset=dataset, config=config, device=device, obj_ids=obj_ids,
            templates_cache=templates_cache, scorer=ref.path("scorer") if config.start == "appearance" else None)

    @classmethod
    def from_onnx(
        cls, export_dir: str | Path, models_dir: str | Path | None = None, dataset: DatasetSource = None,
        config: InferenceConfig | None = None, obj_ids: Sequence[int] | None = None, n_points: int | None = None,
        threads: int | None = None, detector: bool = True, spinning: bool = False,
        templates_cache: str | Path | None = None,
    ) -> "Predictor":
        """The pipeline with the exported networks of ``export_dir`` (``cosy-lite export --out``)
        in onnxruntime on the CPU; crops, rendering, pose updates and ICP as :meth:`from_checkpoints`
        (the same loop, :func:`~cosy_lite.nets.render_and_compare.iterate_poses`).

        Args:
            export_dir: folder with ``manifest.json``, ``coarse.onnx`` [, ``refiner.onnx``,
                ``detector.onnx``, ``scorer.onnx`` (describes the detections of ``start="appearance"``;
                without it the frozen trunk does), ``*.int8.onnx``]; no checkpoint is needed (object ids, crop
                sizes, the label map and the inference settings are in the manifest and the files' metadata).
            models_dir / dataset: the objects' BOP ``models/`` folder, or a dataset (as
                :meth:`from_checkpoints`).
            config: as the class; None: the export's (its manifest's ``inference``); precision
                "fp32", or "int8" (the dynamically quantised pose networks).
            threads: intra-op threads per onnxruntime session (None: its default); the crops and
                pose updates run in torch (its own thread setting).
            detector: use ``detector.onnx`` when the export has one (False: detections are given).
            spinning: let idle onnxruntime threads spin (faster on a quiet machine, much slower on
                a shared one).
            templates_cache: as :meth:`from_checkpoints`.
        Raises OnnxModelError naming the file and field (missing / truncated / mismatched files,
        see :func:`~cosy_lite.inference.onnx_runtime.load_onnx_models`), SetupError when the exported
        models or the object models do not cover the objects, or the scorer was trained against
        templates shaded otherwise than the refiner renders.
        """
        from cosy_lite.export.manifest import Manifest, OnnxModelError
        from cosy_lite.inference.onnx_runtime import load_onnx_models

        manifest = Manifest.read(export_dir)
        config = config or inference_config(manifest.inference, manifest.path)
        precision = config.precision
        if precision not in ("fp32", "int8"):
            raise SetupError(f"precision {precision!r}: the ONNX networks run in fp32 or int8")
        onnx = load_onnx_models(export_dir, threads, precision, detector, spinning)
        meshes = object_meshes(models_dir, dataset)
        role = "coarse" if onnx.coarse is not None else "refiner"
        if onnx.coarse is None and config.start == "coarse":
            raise OnnxModelError(onnx.manifest.path, "models.coarse", "missing: the export has no coarse model "
                                 f"(it has {sorted(onnx.manifest.models)}); export one or use start='templates'")
        first_name = role + ("" if precision == "fp32" else f".{precision}")
        first = onnx.coarse if onnx.coarse is not None else onnx.refiner
        try:
            ids = estimated_obj_ids(obj_ids, first.obj_ids, meshes.obj_ids,  # type: ignore[union-attr]
                                    meshes.models_dir / "models_info.json")
        except SetupError as e:
            raise OnnxModelError(onnx.manifest.path, "argument obj_ids" if obj_ids else f"models.{first_name}.obj_ids",
                                 str(e)) from None
        config = dataclasses.replace(with_refiner(config, onnx.refiner is not None), precision="fp32")
        check_fine_crops(config, onnx.refiner)  # (before the templates are rendered)
        objects, renderer, syms = objects_and_renderer(meshes, ids, n_points, config.icp,
                                                    render_shading(onnx.coarse, onnx.refiner))
        scorer = onnx.scorer if config.start == "appearance" else None  # (unused by other starts)
        if scorer is not None:
            _check_scorer(scorer.path, scorer.obj_ids, scorer.shading, ids, renderer)
        elif config.start == "appearance":  # e.g. an export made before scorer.onnx existed
            warnings.warn(f"{onnx.manifest.path}: no scorer.onnx, so the frozen ImageNet trunk describes the "
                          "detections of start='appearance' (ycbvsynth test AR 0.24 / 0.43 instead of 0.30 / 0.53 "
                          "with its trained scorer): export with --pretrained NAME or --scorer CKPT", stacklevel=2)
        templates = start_templates(config.start, meshes, objects, renderer, templates_cache, scorer)
        return cls(onnx.coarse, onnx.refiner, objects, renderer, onnx.detector, config, syms, "cpu", templates)

    @property
    def backend(self) -> str:
        """"onnx" when the pose networks are onnxruntime sessions, else "torch" (one loop for both:
        :func:`~cosy_lite.nets.render_and_compare.iterate_poses`)."""
        return "torch" if all(isinstance(n, nn.Module) for n in self._nets.values()) else "onnx"

    @property
    def obj_ids(self) -> list[int]:
        """Objects this predictor estimates."""
        return list(self.objects.obj_ids)

    @property
    def needs_masks(self) -> bool:
        """True when :meth:`predict` needs detection masks (``start="templates"``)."""
        return self.start in TEMPLATE_STARTS

    @property
    def reads_masks(self) -> bool:
        """True when :meth:`predict` reads detection masks given with the detections: template starts, ICP,
        ``silhouette_guard``, ``depth_from_mask``."""
        return self.needs_masks or self.config.icp or self.config.depth_from_mask or self.config.silhouette_guard > 0

    def _template_candidates(self, det: Detections, K: np.ndarray, rgb: np.ndarray) -> np.ndarray:
        """``[N,k,4,4]`` float64: the ``n_candidates`` best template poses of each detection (ranked by
        appearance too with ``start="appearance"``: the image ``rgb`` inside each mask)."""
        assert self.templates is not None and det.masks is not None
        masks = det.masks.cpu().numpy().astype(bool)
        empty = ~masks.any(axis=(1, 2))
        if empty.any():  # a detection whose mask has no pixel (the detector's threshold): its box stands in
            masks[empty] = box_masks(det.boxes[torch.from_numpy(empty)], masks.shape[1:])
        return self.templates.match(masks, det.obj_ids.tolist(), K, self.n_candidates,
                                    rgb=rgb if self.start == "appearance" else None).TCO

    # ------------------------------------------------------------------ stages
    def _image_tensor(self, rgb: np.ndarray) -> Tensor:
        """``[1,3,H,W]`` float in [0, 1] on the device."""
        return torch.from_numpy(rgb).to(self.device).permute(2, 0, 1)[None].float().div_(255.0)

    @torch.inference_mode()
    def detect(self, rgb: np.ndarray) -> Detections:
        """The detector's detections of ``rgb [H,W,3]`` uint8, by decreasing score (on CPU);
        ``time_s``: seconds spent."""
        if self.detector is None:
            raise SetupError("no detector loaded: load one (detector=CKPT) or pass detections to predict()")
        clock = Clock(self.device)
        with clock("detection"), flush_denormals():
            if isinstance(self.detector, nn.Module):
                image = self._image_tensor(_as_rgb(rgb))[0]
                det = detect(self.detector, [image], self.config.mask_threshold)[0].to("cpu")
            else:  # onnxruntime (OnnxDetector): numpy in, Detections out
                det = self.detector.detect(_as_rgb(rgb), self.config.mask_threshold)
        order = torch.argsort(det.scores, descending=True, stable=True)
        det = det.select(order)
        det.time_s = clock.seconds["detection"]
        return det

    def _select(self, det: Detections, obj_ids: Sequence[int] | None, from_detector: bool) -> Detections:
        known = set(self.obj_ids)
        wanted = known if obj_ids is None else {int(i) for i in obj_ids}
        unknown = sorted(set(det.obj_ids.tolist()) - known)
        if unknown and not from_detector and obj_ids is None:
            raise ValueError(f"detections of obj_ids {unknown}, which the pose models do not know ({sorted(known)}); "
                             "pass obj_ids=... to keep only some")
        keep = torch.tensor([int(i) in wanted and int(i) in known for i in det.obj_ids.tolist()], dtype=torch.bool)
        return self.detection_filter(det.select(keep))  # (by decreasing score)

    @torch.inference_mode()
    def predict(self, rgb: np.ndarray, K: Any, depth: np.ndarray | None = None, detections: Detections | None = None,
                obj_ids: Sequence[int] | None = None, inst_counts: Mapping[int, int] | None = None) -> PoseEstimates:
        """Poses of the objects in one image.

        Args:
            rgb: [H,W,3] uint8; K: [3,3] intrinsics (px); depth: [H,W] camera z in metres (0 =
                unknown), used by ICP (when enabled) only;
            detections: boxes (+ masks for ICP and template starts; boxes only: the boxes stand in), obj_ids,
                scores; None: run the detector;
            obj_ids: keep only detections of these objects;
            inst_counts: BOP19 ViVo, obj_id -> how many instances to estimate (other objects dropped): each
                object's ``vivo_candidates x inst_count`` best detections are posed
                (:func:`~cosy_lite.inference.vivo.select_candidates`) and the ``inst_count`` the refiner is
                most confident of in its last iteration go on (to ICP, and out); with ``refiner_fine_iterations``
                last, its last iteration before those, which only the detections kept run.
        Returns: :class:`PoseEstimates` by decreasing score (empty when nothing is detected);
        detections whose box has a side under :data:`~cosy_lite.bop.detections.MIN_BOX_SIZE_PX`
        (or a non-finite corner) are skipped with a RuntimeWarning: no pose from a box of nothing.
        """
        rgb, K = _as_rgb(rgb), _as_K(K)
        H, W = rgb.shape[:2]
        clock = Clock(self.device)
        t_start = time.perf_counter()
        from_detector = detections is None
        if detections is None:
            detections = self.detect(rgb)
            clock.seconds["detection"] = detections.time_s
        det = self._select(detections, obj_ids, from_detector)
        if inst_counts is not None:
            det = select_candidates(det, inst_counts, self.config.vivo_candidates, self.config.vivo_score_ratio)
        if (bad := degenerate_boxes(det)).any():
            warnings.warn(f"Predictor: {int(bad.sum())} detection(s) with a box side under {MIN_BOX_SIZE_PX} px or "
                          f"non-finite skipped (no pose estimated): {describe_boxes(det, bad)}", RuntimeWarning,
                          stacklevel=2)
            det = det.select(~bad)
        if len(det) == 0:
            return PoseEstimates.empty(self._timings(clock, t_start))
        one_time = 0.0 if self.templates is None else self.templates.prepare(det.obj_ids.tolist(), progress=True)
        given_masks = det.masks  # what predictions record (not the boxes standing in)
        if self.needs_masks and det.masks is None:
            warnings.warn(f"Predictor: start={self.config.start!r} matches detection masks, but these {len(det)} "
                          "detections are boxes only: the boxes stand in for their masks (a weaker silhouette match)",
                          RuntimeWarning, stacklevel=2)
            det = dataclasses.replace(det, masks=torch.from_numpy(box_masks(det.boxes, (H, W))))
        icp = self.config.icp_settings
        verify = self.config.icp and depth is not None and icp.verify_candidates and icp.check_agreement
        fits_masks = self.config.depth_from_mask or self.config.silhouette_guard > 0
        if fits_masks and given_masks is None:
            warnings.warn(f"Predictor: depth_from_mask / silhouette_guard compare the refined poses with the "
                          f"detections' masks, but these {len(det)} detections are boxes only: the refiner's poses "
                          "are kept", RuntimeWarning, stacklevel=2)
        choose = None  # the refiner's choice among each object's detections (else: the best scored, above)
        if inst_counts is not None and self.config.vivo_candidates > 1:
            choose = _most_confident_of(det, inst_counts)
        with flush_denormals():
            TCO_coarse, TCO, hypotheses, keep = self._poses(
                rgb, K, det, clock, verify, given_masks if fits_masks and self.refiner is not None else None, choose)
        if keep is not None:
            det = det.select(keep)
            given_masks = None if given_masks is None else given_masks[keep]
        icp_results, TCO_before_icp = None, None
        if self.config.icp and depth is not None:
            TCO_before_icp = TCO
            with clock("icp"):
                if hypotheses is not None and verify:
                    TCO, icp_results = self.depth_refinement.refine_hypotheses(hypotheses, K, depth, det, (H, W))
                else:
                    TCO, icp_results = self.depth_refinement.refine(TCO, K, depth, det, (H, W))
        valid = valid_poses(TCO)
        if not valid.all():
            invalid = (~valid).nonzero().flatten().tolist()
            warnings.warn(f"Predictor: invalid poses (NaN/inf, not a rotation or behind the camera) of detections "
                          f"{invalid} (obj_ids {det.obj_ids[invalid].tolist()}); flagged valid=False", RuntimeWarning,
                          stacklevel=2)
        return PoseEstimates(det.obj_ids.clone(), TCO, det.scores.float().clone(), det.boxes.float().clone(), valid,
                             TCO_coarse, self._timings(clock, t_start, one_time), icp_results, TCO_before_icp,
                             None if given_masks is None else given_masks.clone())

    def _poses(self, rgb: np.ndarray, K: Tensor, det: Detections, clock: Clock, verify: bool = False,
               exact_masks: Tensor | None = None, choose: Choice | None = None,
               ) -> tuple[Tensor, Tensor, Tensor | None, Tensor | None]:
        """(after coarse, after refiner) ``[M,4,4]`` float64 on CPU, with several template candidates the
        hypotheses ``[M,k,4,4]`` for ICP (the chosen one's final pose first, then the others after their one
        refiner iteration, or with ``candidate_choice="start"`` as the start stage made them; None with one
        candidate), and the indices ``[M]`` of the detections kept (None: all, ``M = N``). ``verify``: ICP will
        verify the hypotheses (with ``candidate_choice="start"`` they are kept only then). ``exact_masks
        [N,H,W]``: the masks the refined poses are checked against (``silhouette_guard``, ``depth_from_mask``:
        :mod:`~cosy_lite.inference.mask_fit`). ``choose``: which detections go on, from the refiner's confidence
        ``[N]`` (:func:`~cosy_lite.nets.render_and_compare.iterate_poses_scored`; None when none ran), asked
        before the refiner's last iterations on larger crops (``refiner_fine_iterations``: only the detections
        kept run them) or else after its last iteration."""
        t0 = time.perf_counter()
        before = clock.seconds["render"] + clock.seconds["networks"]
        N = len(det)
        rows = self.objects.index(det.obj_ids)
        ids = det.obj_ids.tolist()
        image = self._image_tensor(rgb)  # the image is converted once; each object's crop reads it
        # One copy per object, once (roi_align would copy an expanded view in every iteration).
        images = image.expand(N, -1, -1, -1).contiguous()
        K_b = K.to(self.device, torch.float32)[None].expand(N, 3, 3).contiguous()
        points = self.objects.points[rows.to(self.device)]
        renderer = TimedRenderer(self.renderer, clock)
        TCO_coarse, TCO_init, hypotheses, pick, steps = self._start(rgb, K, det, image, K_b, points, renderer, clock,
                                                                    verify)
        TCO = TCO_init
        refined: list[Tensor] = []  # the refiner's poses after each of its iterations
        confidence = None  # ... and its confidence in the last one
        keep = None

        def select(chosen: Tensor) -> None:  # only the detections kept go on
            nonlocal keep, images, K_b, points, ids, TCO, TCO_coarse, refined, hypotheses, pick, exact_masks
            keep = chosen.to(self.device)
            images, K_b, points, TCO, TCO_coarse = images[keep], K_b[keep], points[keep], TCO[keep], TCO_coarse[keep]
            ids, refined = [ids[i] for i in keep.tolist()], [p[keep] for p in refined]
            hypotheses = None if hypotheses is None else hypotheses[keep]
            pick = None if pick is None else pick[keep]
            exact_masks = None if exact_masks is None else exact_masks[keep.to(exact_masks.device)]

        for role, model, n_iterations in steps:
            net = timed_net(self._nets[role], clock, self.config.channels_last, self.config.precision)
            fine = (FineCrops.of(self.config.refiner_fine_iterations, self.config.refiner_fine_resolution)
                    if role == "refiner" else None)
            first = 1 + self.config.n_refiner_iterations - n_iterations
            for first_i, n_i in _split_before_fine(first, n_iterations, fine if choose is not None else None):
                if first_i > first and choose is not None:  # the choice, before the larger crops
                    select(choose(confidence))
                    choose = None
                poses, score = iterate_poses_scored(
                    net, images, K_b, TCO, ids, points, renderer, n_i, model.crop_resolution,
                    self.config.batch_size, model.output, fine=fine, first_iteration=first_i)
                TCO = poses[-1]
                if role == "refiner":
                    refined, confidence = refined + poses, score.cpu()
            if role == "coarse":
                TCO_coarse = TCO
        if choose is not None:  # after the refiner's last iteration (or the start's, without a refiner)
            select(choose(confidence))
        TCO = self._refined_poses(TCO, refined, K, exact_masks, ids, renderer)
        clock.sync()
        spent = time.perf_counter() - t0 - (clock.seconds["render"] + clock.seconds["networks"] - before)
        clock.seconds["crops"] += spent
        if hypotheses is not None:  # the chosen one's final pose first (ICP tries it before the others)
            at = torch.arange(len(TCO), device=TCO.device)
            hypotheses = hypotheses.clone().double()
            hypotheses[at, pick] = hypotheses[at, 0]
            hypotheses[:, 0] = TCO
            hypotheses = orthonormalise(hypotheses.cpu().reshape(-1, 4, 4)).reshape(hypotheses.shape)
        return orthonormalise(TCO_coarse.cpu()), orthonormalise(TCO.cpu()), hypotheses, None if keep is None else keep.cpu()

    def _start(self, rgb: np.ndarray, K: Tensor, det: Detections, image: Tensor, K_b: Tensor, points: Tensor,
               renderer: Renderer, clock: Clock, verify: bool,
               ) -> tuple[Tensor, Tensor, Tensor | None, Tensor | None, list[tuple[str, PoseModel, int]]]:
        """The start stage of :meth:`_poses`: (start pose, the pose the networks start from ``[N,4,4]``, the
        hypotheses ``[N,k,4,4]`` and the candidate each chose ``[N]`` (None with one), the network steps
        (role, model, iterations) left to run)."""
        N = len(det)
        rows = self.objects.index(det.obj_ids)
        n_refiner = self.config.n_refiner_iterations
        hypotheses, pick = None, None
        steps: list[tuple[str, PoseModel, int]] = []
        if self.start == "coarse":
            assert self.coarse is not None  # (checked when built)
            TCO_init = initial_pose_from_boxes(det.boxes.double().to(self.device), K_b.double(),
                                               self.objects.diameters[rows.to(self.device)].double()).float()
            steps.append(("coarse", self.coarse, 1))
            TCO_coarse = TCO_init
        else:
            # (template matching is part of "crops": the rest of this stage's time, counted once below)
            candidates = torch.from_numpy(self._template_candidates(det, K.numpy(), rgb)).to(self.device)
            if self.config.candidate_choice == "start":  # the start stage's best goes on; the others, as it
                if verify and candidates.shape[1] > 1:  # made them, only for ICP to try
                    hypotheses, pick = candidates.double(), torch.zeros(N, dtype=torch.long, device=self.device)
                candidates = candidates[:, :1]
            if candidates.shape[1] == 1:
                TCO_init = TCO_coarse = candidates[:, 0].float()
            else:
                TCO_coarse, TCO_init, hypotheses, pick = self._choose_candidate(
                    candidates.float(), image, K_b, det.obj_ids.tolist(), points, renderer, clock)
                n_refiner -= 1
        if self.refiner is not None:
            steps.append(("refiner", self.refiner, n_refiner))
        return TCO_coarse, TCO_init, hypotheses, pick, steps

    def _refined_poses(self, TCO: Tensor, refined: list[Tensor], K: Tensor, exact_masks: Tensor | None, ids: list[int],
                       renderer: Renderer) -> Tensor:
        """The refiner's result from ``TCO [N,4,4]`` (its last iteration, or the start when no iteration ran after
        it) and ``refined`` (its poses after each iteration run here): with exact masks, the iteration the
        silhouette guard keeps; its depth divided by the refiner's drift after the iterations that set it
        (``refiner_depth_drift``); with exact masks, fitted to them (``depth_from_mask``)."""
        first = 1 + self.config.n_refiner_iterations - len(refined)  # (the candidates' choice ran the first)
        keep = torch.full((len(TCO),), len(refined) - 1, dtype=torch.long, device=TCO.device)
        if refined and exact_masks is not None and self.config.silhouette_guard > 0:
            keep = guarded_iterations(refined, K, exact_masks, ids, renderer, self.config.silhouette_guard).to(TCO.device)
            TCO = torch.stack(refined)[keep, torch.arange(len(TCO), device=TCO.device)]
        if self.refiner is not None:  # the refiner's own depth bias, measured from GT poses
            drift = torch.tensor([self.config.depth_drift(self.config.depth_iterations(first + j))
                                  for j in range(len(refined))] or [self.config.depth_drift(self.config.depth_iterations())],
                                 dtype=TCO.dtype, device=TCO.device)
            TCO = TCO.clone()
            TCO[:, :3, 3] /= drift[keep.clamp(min=0)][:, None]
        if exact_masks is not None and self.config.depth_from_mask:
            TCO = fit_depth_to_masks(TCO, K, exact_masks, ids, renderer)
        return TCO

    def _choose_candidate(self, candidates: Tensor, image: Tensor, K_b: Tensor, ids: list[int], points: Tensor,
                          renderer: Renderer, clock: Clock) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        """(chosen candidate [N,4,4], it after one refiner iteration [N,4,4], every candidate after one
        iteration [N,k,4,4], the choice [N]) of ``candidates [N,k,4,4]``: the one with the highest
        flow confidence (invalid candidates are not run)."""
        N, k = candidates.shape[:2]
        flat = candidates.reshape(N * k, 4, 4)
        owner = torch.arange(N, device=flat.device).repeat_interleave(k)
        assert self.refiner is not None
        net = timed_net(self._nets["refiner"], clock, self.config.channels_last, self.config.precision)
        refined, score = refine_and_score(net, image.expand(N * k, -1, -1, -1), K_b[owner], flat,
                                          [ids[i] for i in owner.tolist()], points[owner], renderer,
                                          self.refiner.crop_resolution, self.config.batch_size)
        pick = score.view(N, k).argmax(dim=1)
        at = torch.arange(N, device=flat.device)
        refined = refined.view(N, k, 4, 4)
        return candidates[at, pick], refined[at, pick], refined, pick

    @staticmethod
    def _timings(clock: Clock, t_start: float, templates: float = 0.0) -> dict[str, float]:
        """Seconds per stage; ``templates``: the one-time template rendering, apart from the total."""
        out = {k: float(clock.seconds.get(k, 0.0)) for k in TIMING_KEYS}
        out["templates"] = templates
        out["total"] = time.perf_counter() - t_start - templates
        return out
