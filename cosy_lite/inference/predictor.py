"""The pose-estimation pipeline for one RGB(-D) image: detector -> coarse -> refiner -> depth ICP.

Per image: the image is converted to a tensor once; every detected object goes through the
networks together (one batch per iteration, see :func:`~cosy_lite.models.render_and_compare.iterate_poses`,
all crops of an iteration rendered in one call). Starting pose (``start``):

* ``"coarse"`` (CosyPose): canonical rotation and depth from the detection box
  (:func:`~cosy_lite.models.initial_pose.initial_pose_from_boxes`) -> 1 coarse iteration;
* ``"templates"``: the detection mask matched against rendered silhouettes
  (:class:`~cosy_lite.models.silhouette_templates.SilhouetteTemplates`, no network); with
  ``n_candidates`` > 1 the best templates each get one refiner iteration and the one the flow
  refiner is most confident about (:func:`~cosy_lite.models.render_and_compare.refine_and_score`)
  goes on (that iteration counts as the first of ``n_refiner_iterations``);

-> ``n_refiner_iterations`` refiner iterations (CosyPose: 1 + 4) -> optionally point-to-plane ICP
against the measured depth inside each detection mask (:func:`~cosy_lite.inference.icp.refine_poses_icp`).

Robot users: ``Predictor.from_checkpoints(coarse=..., refiner=..., models_dir=...)`` then
``predict(rgb, K)``; no dataset needed, only the BOP ``models/`` folder of the objects (PLY in mm
+ ``models_info.json``). Poses are object-to-camera in metres. Exported networks (``cosy-lite
export``): ``Predictor.from_onnx(export_dir, models_dir=...)`` runs the same pipeline with the
three networks in onnxruntime; its pose iterations are the numpy twin of the torch loop
(:mod:`cosy_lite.inference.iterate_np`: numpy crops, renders and pose updates, no torch op per
iteration; torch only wraps the detections and the results, once per image).
"""

from __future__ import annotations

import copy
import time
import warnings
from collections import defaultdict
from contextlib import contextmanager
from dataclasses import dataclass, field, replace
from functools import cached_property
from pathlib import Path
from typing import Any, Callable, Iterator, Sequence

import numpy as np
import torch
from torch import Tensor, nn

from cosy_lite.bop import io
from cosy_lite.bop.detections import MIN_BOX_SIZE_PX, Detections, degenerate_boxes, describe_boxes
from cosy_lite.errors import BopFormatError, CosyLiteError
from cosy_lite.inference import iterate_np
from cosy_lite.inference.icp import IcpConfig, IcpResult
from cosy_lite.inference.iterate_np import MIN_DEPTH
from cosy_lite.inference.loaders import PoseModel, load_detector, load_pose_model
from cosy_lite.models import initial_pose_np
# torchvision at import, before any rendering: importing it (-> triton's LLVM) after Mesa's llvmpipe
# has rendered crashes the process.
from cosy_lite.models.detector import detect
from cosy_lite.models.initial_pose import initial_pose_from_boxes
from cosy_lite.models.render_and_compare import iterate_poses, refine_and_score
from cosy_lite.models.silhouette_templates import SilhouetteTemplates, file_key


class SetupError(CosyLiteError):
    """A predictor that cannot be built or run as asked (missing model, objects not covered); the
    message names the file."""


TIMING_KEYS = ("detection", "crops", "render", "networks", "icp", "total")
STARTS = ("coarse", "templates")  # where the pose iterations start (see the module doc)


# ----------------------------------------------------------------------------- results


@dataclass
class PoseEstimates:
    """Pose estimates of the objects of one image, by decreasing score.

    obj_ids [N] int64; TCO [N,4,4] float64 object-to-camera (m); scores [N] float32 (the detection
    scores); boxes [N,4] float32 detection boxes x1, y1, x2, y2 (px); valid [N] bool: finite pose,
    rotation matrix, in front of the camera (>= :data:`MIN_DEPTH`) — invalid poses must not be
    written; TCO_coarse [N,4,4] where the refiner started (after the coarse model, or the chosen
    template); icp: one
    :class:`~cosy_lite.inference.icp.IcpResult` per object, or None when ICP did not run;
    TCO_before_icp [N,4,4]: the refiner's poses when ICP ran (None otherwise);
    timings: seconds per stage (:data:`TIMING_KEYS`; "crops" is the rest of the pose iterations:
    crop boxes, roi_align, K_crop, pose updates).
    """

    obj_ids: Tensor
    TCO: Tensor
    scores: Tensor
    boxes: Tensor
    valid: Tensor
    TCO_coarse: Tensor
    timings: dict[str, float] = field(default_factory=dict)
    icp: list[IcpResult] | None = None
    TCO_before_icp: Tensor | None = None

    def __len__(self) -> int:
        return len(self.obj_ids)

    @classmethod
    def empty(cls, timings: dict[str, float] | None = None) -> "PoseEstimates":
        z4 = torch.zeros((0, 4, 4), dtype=torch.float64)
        return cls(torch.zeros(0, dtype=torch.int64), z4, torch.zeros(0), torch.zeros((0, 4)),
                   torch.zeros(0, dtype=torch.bool), z4.clone(), dict(timings or {}))

    def only_valid(self) -> "PoseEstimates":
        """The estimates with a valid pose (same order)."""
        keep = self.valid.nonzero().flatten().tolist()
        icp = None if self.icp is None else [self.icp[i] for i in keep]
        before = None if self.TCO_before_icp is None else self.TCO_before_icp[keep]
        return replace(self, obj_ids=self.obj_ids[keep], TCO=self.TCO[keep], scores=self.scores[keep],
                       boxes=self.boxes[keep], valid=self.valid[keep], TCO_coarse=self.TCO_coarse[keep], icp=icp,
                       TCO_before_icp=before)

    def before_icp(self) -> "PoseEstimates":
        """The estimates as they were before ICP (the refiner's poses; validity and timings without
        ICP); these estimates themselves when ICP did not run."""
        if self.TCO_before_icp is None:
            return self
        timings = dict(self.timings, total=self.timings.get("total", 0.0) - self.timings.get("icp", 0.0), icp=0.0)
        return replace(self, TCO=self.TCO_before_icp, valid=valid_poses(self.TCO_before_icp), icp=None,
                       TCO_before_icp=None, timings=timings)


def valid_poses(TCO: Tensor, rotation_tol: float = 1e-3, min_depth: float = MIN_DEPTH) -> Tensor:
    """``[N]`` bool: ``TCO [N,4,4]`` finite, ``R`` orthonormal with det +1 (within ``rotation_tol``),
    z >= ``min_depth`` (m)."""
    TCO = TCO.double()
    finite = torch.isfinite(TCO).all(dim=(1, 2))
    R = torch.where(finite[:, None, None], TCO[:, :3, :3], torch.eye(3, dtype=TCO.dtype, device=TCO.device))
    eye = torch.eye(3, dtype=TCO.dtype, device=TCO.device)
    ortho = (R @ R.transpose(1, 2) - eye).abs().amax(dim=(1, 2)) <= rotation_tol
    det = (torch.linalg.det(R) - 1.0).abs() <= rotation_tol
    return finite & ortho & det & (TCO[:, 2, 3].nan_to_num(nan=-1.0) >= min_depth)


def orthonormalise(TCO: Tensor) -> Tensor:
    """``TCO [N,4,4]`` with each finite rotation replaced by the nearest rotation matrix (SVD, float64)."""
    TCO = TCO.double().clone()
    ok = torch.isfinite(TCO).all(dim=(1, 2))
    if ok.any():
        U, _, Vh = torch.linalg.svd(TCO[ok, :3, :3])
        D = torch.ones(int(ok.sum()), 3, dtype=TCO.dtype, device=TCO.device)
        D[:, 2] = torch.sign(torch.linalg.det(U @ Vh))
        TCO[ok, :3, :3] = U @ torch.diag_embed(D) @ Vh
    return TCO


# ----------------------------------------------------------------------------- models of the objects


@dataclass
class ObjectModels:
    """The BOP ``models/`` folder of the objects (PLY in mm, ``models_info.json``), read lazily.

    Has what :meth:`cosy_lite.models.object_table.ObjectTable.from_dataset` reads of a dataset
    (``models_dir``, ``models_info``, ``load_model``), so no dataset folder is needed.
    """

    models_dir: Path

    def __post_init__(self) -> None:
        self.models_dir = Path(self.models_dir)
        if not (self.models_dir / "models_info.json").is_file():
            raise BopFormatError(self.models_dir / "models_info.json", "", "not found (a BOP models/ folder is needed)")

    @cached_property
    def models_info(self) -> dict[int, io.ModelInfo]:
        return io.load_models_info(self.models_dir / "models_info.json")

    @property
    def obj_ids(self) -> list[int]:
        return sorted(self.models_info)

    def load_model(self, obj_id: int):
        """trimesh.Trimesh in metres."""
        return io.load_model(self.models_dir / f"obj_{int(obj_id):06d}.ply")


# ----------------------------------------------------------------------------- timing


class _Clock:
    """Accumulates seconds per key; waits for the device before reading the clock (CUDA is asynchronous)."""

    def __init__(self, device: torch.device):
        self.device = device
        self.seconds: dict[str, float] = defaultdict(float)

    def sync(self) -> None:
        if self.device.type == "cuda":
            torch.cuda.synchronize(self.device)

    @contextmanager
    def __call__(self, key: str) -> Iterator[None]:
        self.sync()
        t0 = time.perf_counter()
        try:
            yield
        finally:
            self.sync()
            self.seconds[key] += time.perf_counter() - t0


class _TimedRenderer:
    """A renderer whose ``render`` / ``render_tensors`` calls are timed under "render"."""

    def __init__(self, renderer: Any, clock: _Clock):
        self.renderer, self.clock = renderer, clock

    def render(self, *args: Any, **kwargs: Any):
        with self.clock("render"):
            return self.renderer.render(*args, **kwargs)

    def render_tensors(self, *args: Any, **kwargs: Any):
        with self.clock("render"):
            return self.renderer.render_tensors(*args, **kwargs)


# name -> autocast dtype of the pose networks' forward pass (None: full fp32)
PRECISIONS: dict[str, torch.dtype | None] = {"fp32": None, "bf16": torch.bfloat16}


def _timed_numpy_net(run: Callable[[np.ndarray], np.ndarray], clock: _Clock) -> Callable[[np.ndarray], np.ndarray]:
    """A numpy network (``OnnxPoseNet.run``: ``[B,6,h,w]`` float32 -> ``[B,9]``) timed under "networks"."""

    def timed(x: np.ndarray) -> np.ndarray:
        with clock("networks"):
            return run(x)

    return timed


def _timed_net(net: nn.Module | Callable[[Tensor], Tensor], clock: _Clock, channels_last: bool, precision: str):
    """``net`` as a function of ``[B,6,h,w]`` float32 -> ``[B,9]`` float32, timed under "networks".
    A ``net`` that is not a torch module (an onnxruntime session) is only timed."""
    if not isinstance(net, nn.Module):
        def run_plain(x: Tensor) -> Tensor:
            with clock("networks"):
                return net(x).float()

        return run_plain
    dtype = PRECISIONS[precision]
    memory_format = torch.channels_last if channels_last else torch.contiguous_format

    def run(x: Tensor) -> Tensor:
        with clock("networks"), torch.autocast(x.device.type, dtype=dtype or torch.float32, enabled=dtype is not None):
            return net(x.contiguous(memory_format=memory_format)).float()

    return run


def inference_net(net: nn.Module, device: torch.device, channels_last: bool = True, fuse_bn: bool = True) -> nn.Module:
    """A copy of a pose network for inference on ``device``, in eval mode: BatchNorm folded into the
    preceding convolutions of ``net.backbone.net`` (``torch.fx``; same outputs to ~1e-6 relative,
    ~1.2-1.5x faster on CPU), optionally channels-last. The given module is left as it is."""
    out = copy.deepcopy(net).eval().to(device)
    backbone = getattr(getattr(out, "backbone", None), "net", None)
    if fuse_bn and isinstance(backbone, nn.Module):
        from torch.fx.experimental.optimization import fuse

        try:
            out.backbone.net = fuse(backbone)
        except Exception:  # noqa: BLE001 - a backbone torch.fx cannot trace stays unfused (only slower)
            pass
    return out.to(memory_format=torch.channels_last if channels_last else torch.contiguous_format)


@contextmanager
def _flush_denormals() -> Iterator[None]:
    """Denormal floats flushed to zero on CPU (x86 arithmetic on them is ~100x slower; untrained
    nets produce many), back to PyTorch's default (off) afterwards."""
    torch.set_flush_denormal(True)
    try:
        yield
    finally:
        torch.set_flush_denormal(False)


# ----------------------------------------------------------------------------- the predictor


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


def _box_masks(boxes: Tensor, size: tuple[int, int]) -> np.ndarray:
    """``[N,H,W]`` bool masks filling ``boxes [N,4]`` (x1, y1, x2, y2 px)."""
    H, W = size
    masks = np.zeros((len(boxes), H, W), dtype=bool)
    for k, (x1, y1, x2, y2) in enumerate(boxes.double().tolist()):
        r0, r1 = max(0, int(np.floor(y1))), max(0, int(np.ceil(y2)))
        c0, c1 = max(0, int(np.floor(x1))), max(0, int(np.ceil(x2)))
        masks[k, r0:r1, c0:c1] = True
    return masks


def _object_models(models_dir: str | Path | None, dataset: Any) -> ObjectModels:
    """The objects' BOP ``models/`` folder: ``models_dir`` or ``dataset``'s (exactly one given)."""
    from cosy_lite.bop.dataset import BopDataset

    if (models_dir is None) == (dataset is None):
        raise SetupError("give exactly one of models_dir (a BOP models/ folder) and dataset")
    if dataset is not None:
        ds = dataset if isinstance(dataset, BopDataset) else BopDataset(Path(dataset))
        return ObjectModels(ds.models_dir)
    return ObjectModels(Path(models_dir))


def render_shading(coarse: PoseModel | None, refiner: PoseModel | None) -> str:
    """The renderer shading the pose networks were trained with (SetupError if they differ)."""
    if coarse is None or refiner is None:
        model = coarse or refiner
        if model is None:
            raise SetupError("no pose model given (a coarse and/or a refiner checkpoint is needed)")
        return model.render_shading
    if refiner.render_shading != coarse.render_shading:
        raise SetupError(f"the coarse model ({coarse.describe()}) was trained on {coarse.render_shading!r} renderings, "
                         f"the refiner ({refiner.describe()}) on {refiner.render_shading!r}: they need one renderer")
    return coarse.render_shading


def _objects_renderer(models: ObjectModels, ids: list[int], n_points: int | None, icp: bool,
                      shading: str = "flat") -> tuple[Any, Any, Any]:
    """(ObjectTable of ``ids``, a renderer of ``models`` with ``shading``, ICP symmetry sets or None)."""
    from cosy_lite.geometry.symmetries import symmetry_transforms
    from cosy_lite.models.object_table import ObjectTable
    from cosy_lite.render.renderer import PyrenderRenderer

    kwargs = {} if n_points is None else {"n_points": n_points}
    objects = ObjectTable.from_dataset(models, ids, **kwargs)  # type: ignore[arg-type]
    syms = {i: symmetry_transforms(models.models_info[i]) for i in ids} if icp else None
    return objects, PyrenderRenderer(models_dir=models.models_dir, shading=shading), syms


def _silhouette_templates(start: str, models: ObjectModels, objects: Any, renderer: Any,
                          cache_dir: str | Path | None) -> SilhouetteTemplates | None:
    """The templates for ``start="templates"`` (None otherwise), cached in ``cache_dir`` by the hash
    of each object's mesh file."""
    if start != "templates":
        return None
    keys = {} if cache_dir is None else {i: file_key(models.models_dir / f"obj_{int(i):06d}.ply") for i in objects.obj_ids}
    return SilhouetteTemplates(renderer, objects.obj_ids, objects.diameters.detach().cpu().double().tolist(),
                               cache_dir=cache_dir, model_keys=keys)


class Predictor:
    """Detector -> coarse -> refiner -> optional depth ICP, for single images.

    Args:
        coarse, refiner: the pose networks (:class:`~cosy_lite.inference.loaders.PoseModel`; torch
            modules, or onnxruntime sessions from :meth:`from_onnx`); refiner None: coarse only;
            coarse None: only with ``start="templates"`` (the coarse network is not used there).
        objects: :class:`~cosy_lite.models.object_table.ObjectTable` of the objects to estimate
            (model points for the crops, diameters for the starting depth).
        renderer: batched renderer of the same objects (:class:`~cosy_lite.render.renderer.PyrenderRenderer`).
        detector: :class:`~cosy_lite.models.detector.Detector`, an
            :class:`~cosy_lite.export.onnx_models.OnnxDetector`, or None (detections then have to be given).
        n_refiner_iterations: refiner iterations after the coarse one (CosyPose: 4).
        icp: run depth ICP when a depth image is given; icp_config: its settings.
        icp_symmetries: obj_id -> symmetry set [S,4,4] (m) for ICP (None: no symmetry handling).
        device: where the networks run; batch_size: crops per network call.
        channels_last: run the networks in channels-last memory format (same numbers, faster
            convolutions on CPU); fuse_bn: fold BatchNorm into the convolutions. Both act on copies
            of the networks (:func:`inference_net`); the given modules are not changed.
        precision: a key of :data:`PRECISIONS`: "fp32", or "bf16" autocast of the networks'
            forward pass (about 2x faster on CPUs with AVX512-BF16; the pose updates stay fp32).
        start: a key of :data:`STARTS` (see the module doc); "templates" needs detection masks.
        n_candidates: templates tried per detection (``start="templates"``; > 1 needs a flow refiner).
        templates: the :class:`~cosy_lite.models.silhouette_templates.SilhouetteTemplates` to match
            (None: 2,048 per object, rendered with ``renderer`` on first use of each object).
    """

    def __init__(self, coarse: PoseModel, refiner: PoseModel | None, objects: Any, renderer: Any,
                 detector: Any = None, n_refiner_iterations: int = 4, icp: bool = False,
                 icp_config: IcpConfig | None = None, icp_symmetries: dict[int, np.ndarray] | None = None,
                 device: str | torch.device = "cpu", batch_size: int = 32, channels_last: bool = True,
                 precision: str = "fp32", fuse_bn: bool = True, start: str = "coarse", n_candidates: int = 1,
                 templates: SilhouetteTemplates | None = None):
        if start not in STARTS:
            raise ValueError(f"start must be one of {STARTS}, got {start!r}")
        if coarse is None and start == "coarse":
            raise SetupError("start='coarse' needs a coarse model (or use start='templates')")
        if n_candidates < 1:
            raise ValueError(f"n_candidates must be >= 1, got {n_candidates}")
        if n_candidates > 1 and (start != "templates" or refiner is None or refiner.output != "flow"
                                 or n_refiner_iterations < 1):
            raise SetupError(f"n_candidates = {n_candidates} needs start='templates' and a flow refiner "
                             f"(net.arch=flow) with at least one iteration: its confidence ranks the candidates")
        if n_refiner_iterations < 0:
            raise ValueError(f"n_refiner_iterations must be >= 0, got {n_refiner_iterations}")
        if refiner is None and n_refiner_iterations > 0:
            raise ValueError(f"n_refiner_iterations = {n_refiner_iterations} but no refiner model given")
        self.device = torch.device(device)
        self.coarse, self.refiner, self.detector = coarse, refiner, detector
        self.objects = objects.to(self.device)
        self.renderer = renderer
        self.n_refiner_iterations = int(n_refiner_iterations)
        self.icp, self.icp_config = bool(icp), icp_config or IcpConfig()
        self.icp_symmetries = icp_symmetries
        self.batch_size = int(batch_size)
        if precision not in PRECISIONS:
            raise ValueError(f"precision must be one of {sorted(PRECISIONS)}, got {precision!r}")
        self.channels_last, self.precision = bool(channels_last), precision
        self.start, self.n_candidates = start, int(n_candidates)
        if start == "templates" and templates is None:
            templates = SilhouetteTemplates(renderer, self.objects.obj_ids,
                                            self.objects.diameters.detach().cpu().double().tolist())
        self.templates = templates
        if isinstance(detector, nn.Module):  # else an onnxruntime detector (OnnxDetector)
            detector.to(self.device).eval()
        self._nets: dict[str, nn.Module | Callable[[Tensor], Tensor]] = {}
        for role, m in (("coarse", coarse), ("refiner", refiner)):
            if m is not None:
                self._nets[role] = (inference_net(m.net, self.device, self.channels_last, fuse_bn)
                                    if isinstance(m.net, nn.Module) else m.net)
                missing = sorted(set(self.objects.obj_ids) - set(m.obj_ids))
                if missing:
                    raise SetupError(f"{m.describe()}: the {m.kind} model was not trained on obj_ids {missing} "
                                     f"(it knows {m.obj_ids})")
        self._warned_box_masks = False

    # ------------------------------------------------------------------ construction
    @classmethod
    def from_checkpoints(
        cls, detector: str | Path | None = None, coarse: str | Path | None = None,
        refiner: str | Path | None = None, models_dir: str | Path | None = None, dataset: Any = None,
        device: str | torch.device = "cpu", n_refiner_iterations: int = 4, icp: bool = False,
        icp_config: IcpConfig | None = None, obj_ids: Sequence[int] | None = None, n_points: int | None = None,
        precision: str = "fp32", start: str = "coarse", n_candidates: int = 1,
        templates_cache: str | Path | None = None,
    ) -> "Predictor":
        """Load the checkpoints and the object models.

        Args:
            detector, coarse, refiner: checkpoint files (``train.py`` outputs); detector None:
                detections are passed to :meth:`predict`; refiner None: coarse only.
            models_dir: a BOP ``models/`` folder, or ``dataset``: a
                :class:`~cosy_lite.bop.dataset.BopDataset` or dataset folder (its ``models/``).
            obj_ids: objects to estimate (default: those of the coarse checkpoint).
            n_points: model points per object for the crop boxes (default: ObjectTable's).
            precision: "fp32" or "bf16" (see the class); start, n_candidates: as the class
                (``start="templates"`` needs no coarse checkpoint); templates_cache: a folder where
                the rendered templates are kept between runs (None: rendered in every run).
        Raises CheckpointError naming the file (missing, wrong kind, unreadable), SetupError when
        a checkpoint does not cover the objects.
        """
        if coarse is None and (start != "templates" or refiner is None):
            raise SetupError("a coarse checkpoint is needed (coarse=...), or start='templates' with a refiner")
        models = _object_models(models_dir, dataset)
        coarse_model = None if coarse is None else load_pose_model(coarse, "coarse", device)
        refiner_model = None if refiner is None else load_pose_model(refiner, "refiner", device)
        if refiner_model is None:
            n_refiner_iterations = 0
        first = coarse_model or refiner_model
        ids = sorted(int(i) for i in obj_ids) if obj_ids else list(first.obj_ids)  # type: ignore[union-attr]
        unknown = sorted(set(ids) - set(models.obj_ids))
        if unknown:
            raise SetupError(f"{models.models_dir / 'models_info.json'}: no models of obj_ids {unknown}")
        objects, renderer, syms = _objects_renderer(models, ids, n_points, icp,
                                                    render_shading(coarse_model, refiner_model))
        det = None if detector is None else load_detector(detector, device)
        templates = _silhouette_templates(start, models, objects, renderer, templates_cache)
        return cls(coarse_model, refiner_model, objects, renderer, det, n_refiner_iterations, icp, icp_config,
                   syms, device, precision=precision, start=start, n_candidates=n_candidates, templates=templates)

    @classmethod
    def from_pretrained(
        cls, name: str, models_dir: str | Path | None = None, dataset: Any = None, detector: bool = True,
        device: str | torch.device = "cpu", icp: bool = False, icp_config: IcpConfig | None = None,
        obj_ids: Sequence[int] | None = None, precision: str = "fp32", start: str | None = None,
        n_candidates: int | None = None, n_refiner_iterations: int | None = None,
        templates_cache: str | Path | None = None,
    ) -> "Predictor":
        """The shipped reference models ``name`` (:mod:`cosy_lite.inference.reference_models`, e.g.
        ``"ycbvsynth"``) with the set's inference settings (start poses, candidates, refiner
        iterations) where ``start`` / ``n_candidates`` / ``n_refiner_iterations`` are None.

        detector: use the set's detector (False: detections are passed to :meth:`predict`); the
        other arguments as :meth:`from_checkpoints`. Raises ReferenceModelError for an unknown name.
        """
        from cosy_lite.inference.reference_models import reference_models

        ref = reference_models(name)
        start = start or ref.setting("start")
        if n_candidates is None:
            n_candidates = ref.setting("n_candidates") if start == ref.setting("start") else 1
        if n_refiner_iterations is None:
            n_refiner_iterations = ref.setting("n_refiner_iterations")
        return cls.from_checkpoints(
            detector=ref.path("detector") if detector else None, coarse=ref.path("coarse") if start == "coarse" else None,
            refiner=ref.path("refiner"), models_dir=models_dir, dataset=dataset, device=device,
            n_refiner_iterations=n_refiner_iterations, icp=icp, icp_config=icp_config, obj_ids=obj_ids,
            precision=precision, start=start, n_candidates=n_candidates, templates_cache=templates_cache)

    @classmethod
    def from_onnx(
        cls, export_dir: str | Path, models_dir: str | Path | None = None, dataset: Any = None,
        n_refiner_iterations: int = 4, icp: bool = False, icp_config: IcpConfig | None = None,
        obj_ids: Sequence[int] | None = None, n_points: int | None = None, threads: int | None = None,
        precision: str = "fp32", detector: bool = True, spinning: bool = False, start: str = "coarse",
        n_candidates: int = 1, templates_cache: str | Path | None = None,
    ) -> "Predictor":
        """The pipeline with the exported networks of ``export_dir`` (``cosy-lite export --out``)
        in onnxruntime on the CPU; the pose iterations in numpy (:mod:`~cosy_lite.inference.iterate_np`:
        the crops, rendering and pose updates of :meth:`from_checkpoints`, no torch op per iteration);
        ICP as there.

        Args:
            export_dir: folder with ``manifest.json``, ``coarse.onnx`` [, ``refiner.onnx``,
                ``detector.onnx``, ``*.int8.onnx``]; no checkpoint is needed (object ids, crop
                sizes and the label map are in the files' metadata).
            models_dir / dataset: the objects' BOP ``models/`` folder, or a dataset (as
                :meth:`from_checkpoints`).
            threads: intra-op threads per onnxruntime session (None: its default); the numpy crops
                and pose updates run in the calling thread (torch's threads are not used).
            precision: "fp32", or "int8" (the dynamically quantised pose networks).
            detector: use ``detector.onnx`` when the export has one (False: detections are given).
            spinning: let idle onnxruntime threads spin (faster on a quiet machine, much slower on
                a shared one).
            start, n_candidates, templates_cache: as :meth:`from_checkpoints`.
        Raises OnnxModelError naming the file and field (missing / truncated / mismatched files,
        see :func:`~cosy_lite.inference.loaders.load_onnx_models`), SetupError when the exported
        models or the object models do not cover the objects.
        """
        from cosy_lite.export.manifest import OnnxModelError
        from cosy_lite.inference.loaders import load_onnx_models

        onnx = load_onnx_models(export_dir, threads, precision, detector, spinning)
        models = _object_models(models_dir, dataset)
        role = "coarse" if onnx.coarse is not None else "refiner"
        if onnx.coarse is None and start == "coarse":
            raise OnnxModelError(onnx.manifest.path, "models.coarse", "missing: the export has no coarse model "
                                 f"(it has {sorted(onnx.manifest.models)}); export one or use start='templates'")
        first_name = role + ("" if precision == "fp32" else f".{precision}")
        first = onnx.coarse if onnx.coarse is not None else onnx.refiner
        ids = sorted(int(i) for i in obj_ids) if obj_ids else list(first.obj_ids)  # type: ignore[union-attr]
        unknown = sorted(set(ids) - set(models.obj_ids))
        if unknown:
            field_ = "argument obj_ids" if obj_ids else f"models.{first_name}.obj_ids"
            raise OnnxModelError(onnx.manifest.path, field_, f"obj_ids {unknown} have no model in "
                                 f"{models.models_dir / 'models_info.json'} (it has {models.obj_ids})")
        if onnx.refiner is None:
            n_refiner_iterations = 0
        objects, renderer, syms = _objects_renderer(models, ids, n_points, icp, render_shading(onnx.coarse, onnx.refiner))
        templates = _silhouette_templates(start, models, objects, renderer, templates_cache)
        return cls(onnx.coarse, onnx.refiner, objects, renderer, onnx.detector, n_refiner_iterations, icp,
                   icp_config, syms, "cpu", precision="fp32", start=start, n_candidates=n_candidates,
                   templates=templates)

    @property
    def backend(self) -> str:
        """"onnx" when the pose networks run in onnxruntime (the numpy loop), else "torch"."""
        return "onnx" if self.numpy_loop else "torch"

    @property
    def numpy_loop(self) -> bool:
        """True when every pose network has a numpy ``run`` (onnxruntime sessions): the pose iterations
        then run in numpy (:mod:`~cosy_lite.inference.iterate_np`), else in torch."""
        return all(callable(getattr(n, "run", None)) for n in self._nets.values())

    @cached_property
    def _object_arrays(self) -> tuple[dict[int, int], np.ndarray, np.ndarray]:
        """(obj_id -> row, points [O,N,3] float64 (m), diameters [O] float64 (m)) of the objects, for the numpy loop."""
        rows = {int(o): k for k, o in enumerate(self.objects.obj_ids)}
        return (rows, self.objects.points.detach().cpu().double().numpy(),
                self.objects.diameters.detach().cpu().double().numpy())

    @property
    def obj_ids(self) -> list[int]:
        """Objects this predictor estimates."""
        return list(self.objects.obj_ids)

    @property
    def needs_masks(self) -> bool:
        """True when :meth:`predict` needs detection masks (``start="templates"``)."""
        return self.start == "templates"

    def _template_candidates(self, det: Detections, K: np.ndarray) -> np.ndarray:
        """``[N,k,4,4]`` float64: the ``n_candidates`` best template poses of each detection."""
        assert self.templates is not None and det.masks is not None
        masks = det.masks.cpu().numpy().astype(bool)
        empty = ~masks.any(axis=(1, 2))
        if empty.any():  # a detection whose mask has no pixel (the detector's threshold): its box stands in
            masks[empty] = _box_masks(det.boxes[torch.from_numpy(empty)], masks.shape[1:])
        return self.templates.match(masks, det.obj_ids.tolist(), K, self.n_candidates).TCO

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
        clock = _Clock(self.device)
        with clock("detection"), _flush_denormals():
            if isinstance(self.detector, nn.Module):
                det = detect(self.detector, [self._image_tensor(_as_rgb(rgb))[0]])[0].to("cpu")
            else:  # onnxruntime (OnnxDetector): numpy in, Detections out
                det = self.detector.detect(_as_rgb(rgb))
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
        det = det.select(keep)
        return det.select(torch.argsort(det.scores, descending=True, stable=True))

    @torch.inference_mode()
    def predict(self, rgb: np.ndarray, K: Any, depth: np.ndarray | None = None, detections: Detections | None = None,
                obj_ids: Sequence[int] | None = None) -> PoseEstimates:
        """Poses of the objects in one image.

        Args:
            rgb: [H,W,3] uint8; K: [3,3] intrinsics (px); depth: [H,W] camera z in metres (0 =
                unknown), used by ICP (when enabled) only;
            detections: boxes (+ masks for ICP), obj_ids, scores; None: run the detector;
            obj_ids: keep only detections of these objects.
        Returns: :class:`PoseEstimates` by decreasing score (empty when nothing is detected);
        detections whose box has a side under :data:`~cosy_lite.bop.detections.MIN_BOX_SIZE_PX`
        (or a non-finite corner) are skipped with a RuntimeWarning: no pose from a box of nothing.
        """
        rgb, K = _as_rgb(rgb), _as_K(K)
        H, W = rgb.shape[:2]
        clock = _Clock(self.device)
        t_start = time.perf_counter()
        from_detector = detections is None
        if from_detector:
            detections = self.detect(rgb)
            clock.seconds["detection"] = detections.time_s
        det = self._select(detections, obj_ids, from_detector)
        if (bad := degenerate_boxes(det)).any():
            warnings.warn(f"Predictor: {int(bad.sum())} detection(s) with a box side under {MIN_BOX_SIZE_PX} px or "
                          f"non-finite skipped (no pose estimated): {describe_boxes(det, bad)}", RuntimeWarning,
                          stacklevel=2)
            det = det.select(~bad)
        if len(det) == 0:
            return PoseEstimates.empty(self._timings(clock, t_start))
        if self.needs_masks and det.masks is None:
            raise ValueError("start='templates' matches the detection masks, but these detections have none "
                             "(give detections with masks, e.g. oracle or BOP22 JSON detections with 'segmentation')")
        with _flush_denormals():
            if self.numpy_loop:
                TCO_coarse, TCO, hypotheses = self._poses_np(rgb, K.numpy(), det, clock)
                TCO_coarse, TCO = torch.from_numpy(TCO_coarse), torch.from_numpy(TCO)
                hypotheses = None if hypotheses is None else torch.from_numpy(hypotheses)
            else:
                TCO_coarse, TCO, hypotheses = self._poses(rgb, K, det, clock)
        icp_results, TCO_before_icp = None, None
        if self.icp and depth is not None:
            TCO_before_icp = TCO
            with clock("icp"):
                if hypotheses is not None and self.icp_config.verify_candidates and self.icp_config.check_agreement:
                    TCO, icp_results = self._icp_hypotheses(hypotheses, K, depth, det, (H, W))
                else:
                    TCO, icp_results = self._icp(TCO, K, depth, det, (H, W))
        valid = valid_poses(TCO)
        if not valid.all():
            bad = (~valid).nonzero().flatten().tolist()
            warnings.warn(f"Predictor: invalid poses (NaN/inf, not a rotation or behind the camera) of "
                          f"detections {bad} (obj_ids {det.obj_ids[bad].tolist()}); flagged valid=False", RuntimeWarning, stacklevel=2)
        return PoseEstimates(det.obj_ids.clone(), TCO, det.scores.float().clone(), det.boxes.float().clone(), valid,
                             TCO_coarse, self._timings(clock, t_start), icp_results, TCO_before_icp)

    def _poses(self, rgb: np.ndarray, K: Tensor, det: Detections,
               clock: _Clock) -> tuple[Tensor, Tensor, Tensor | None]:
        """(after coarse, after refiner) ``[N,4,4]`` float64 on CPU, and with several template
        candidates the hypotheses ``[N,k,4,4]`` for ICP: the chosen one's final pose, the others
        after their one refiner iteration (None with one candidate)."""
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
        renderer = _TimedRenderer(self.renderer, clock)
        n_refiner = self.n_refiner_iterations
        hypotheses, pick = None, None
        if self.start == "coarse":
            TCO_init = initial_pose_from_boxes(det.boxes.double().to(self.device), K_b.double(),
                                               self.objects.diameters[rows.to(self.device)].double()).float()
            steps = [("coarse", self.coarse, 1)]
            TCO_coarse = TCO_init
        else:
            with clock("crops"):
                candidates = torch.from_numpy(self._template_candidates(det, K.numpy())).to(self.device)
            if candidates.shape[1] == 1:
                TCO_init = TCO_coarse = candidates[:, 0].float()
            else:
                TCO_coarse, TCO_init, hypotheses, pick = self._choose_candidate(candidates.float(), image, K_b, ids,
                                                                                points, renderer, clock)
                n_refiner -= 1
            steps = []
        if self.refiner is not None:
            steps.append(("refiner", self.refiner, n_refiner))
        TCO = TCO_init
        for role, model, n_iterations in steps:
            net = _timed_net(self._nets[role], clock, self.channels_last, self.precision)
            for _ in range(n_iterations):  # one at a time: a pose gone invalid is not rendered again
                live = valid_poses(TCO).nonzero().flatten().tolist()
                if not live:
                    break
                if len(live) == N:
                    TCO = iterate_poses(net, images, K_b, TCO, ids, points, renderer, 1, model.crop_resolution,
                                        self.batch_size, model.output)[-1]
                    continue
                sel = torch.tensor(live, device=TCO.device)
                new = iterate_poses(net, images[sel], K_b[sel], TCO[sel], [ids[i] for i in live],
                                    points[sel], renderer, 1, model.crop_resolution, self.batch_size, model.output)[-1]
                TCO = TCO.clone()
                TCO[sel] = new
            if role == "coarse":
                TCO_coarse = TCO
        clock.sync()
        spent = time.perf_counter() - t0 - (clock.seconds["render"] + clock.seconds["networks"] - before)
        clock.seconds["crops"] += spent
        if hypotheses is not None:
            hypotheses = hypotheses.clone()
            hypotheses[torch.arange(N, device=TCO.device), pick] = TCO
            hypotheses = orthonormalise(hypotheses.cpu().double().reshape(-1, 4, 4)).reshape(hypotheses.shape)
        return orthonormalise(TCO_coarse.cpu()), orthonormalise(TCO.cpu()), hypotheses

    def _choose_candidate(self, candidates: Tensor, image: Tensor, K_b: Tensor, ids: list[int], points: Tensor,
                          renderer: Any, clock: _Clock) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        """(chosen candidate [N,4,4], it after one refiner iteration [N,4,4], every candidate after one
        iteration [N,k,4,4], the choice [N]) of ``candidates [N,k,4,4]``: the one with the highest
        flow confidence (invalid candidates are not run)."""
        N, k = candidates.shape[:2]
        flat = candidates.reshape(N * k, 4, 4)
        owner = torch.arange(N, device=flat.device).repeat_interleave(k)
        refined = flat.clone()
        score = torch.full((N * k,), -1.0, dtype=torch.float64, device=flat.device)
        live = valid_poses(flat).nonzero().flatten()
        if len(live):
            assert self.refiner is not None
            net = _timed_net(self._nets["refiner"], clock, self.channels_last, self.precision)
            own = owner[live]
            new, conf = refine_and_score(net, image.expand(len(live), -1, -1, -1), K_b[own], flat[live],
                                         [ids[i] for i in own.tolist()], points[own], renderer,
                                         self.refiner.crop_resolution, self.batch_size)
            refined[live], score[live] = new.to(refined.dtype), conf
        pick = score.view(N, k).argmax(dim=1)
        at = torch.arange(N, device=flat.device)
        refined = refined.view(N, k, 4, 4)
        return candidates[at, pick], refined[at, pick], refined, pick

    def _poses_np(self, rgb: np.ndarray, K: np.ndarray, det: Detections,
                  clock: _Clock) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
        """As :meth:`_poses` with numpy networks and no torch op per iteration (one image, ``K [3,3]``):
        (after coarse, after refiner) ``[N,4,4]`` float64 and the hypotheses ``[N,k,4,4]`` or None."""
        t0 = time.perf_counter()
        before = clock.seconds["render"] + clock.seconds["networks"]
        lookup, all_points, all_diameters = self._object_arrays
        ids = [int(i) for i in det.obj_ids.tolist()]
        rows = np.array([lookup[i] for i in ids], dtype=np.int64)
        N = len(ids)
        image = iterate_np.image_array(rgb)  # converted once; each object's crop reads it
        K_b = np.broadcast_to(np.asarray(K, dtype=np.float64), (N, 3, 3))
        points = all_points[rows]
        renderer = _TimedRenderer(self.renderer, clock)
        n_refiner = self.n_refiner_iterations
        hypotheses, pick = None, None
        if self.start == "coarse":
            TCO = initial_pose_np.initial_pose_from_boxes(det.boxes.double().numpy(), K_b, all_diameters[rows])
            TCO_coarse = TCO
            steps = [("coarse", self.coarse, 1)]
        else:
            with clock("crops"):
                candidates = self._template_candidates(det, np.asarray(K, dtype=np.float64))
            if candidates.shape[1] == 1:
                TCO = TCO_coarse = candidates[:, 0]
            else:
                TCO_coarse, TCO, hypotheses, pick = self._choose_candidate_np(candidates, image, K_b, ids, points,
                                                                              renderer, clock)
                n_refiner -= 1
            steps = []
        if self.refiner is not None:
            steps.append(("refiner", self.refiner, n_refiner))
        for role, model, n_iterations in steps:
            net = _timed_numpy_net(self._nets[role].run, clock)  # type: ignore[union-attr]
            for _ in range(n_iterations):  # one at a time: a pose gone invalid is not rendered again
                live = np.flatnonzero(iterate_np.valid_poses(TCO))
                if len(live) == 0:
                    break
                new = iterate_np.iterate_poses(net, image, K_b[live], TCO[live], [ids[i] for i in live],
                                               points[live], renderer, 1, model.crop_resolution, self.batch_size,
                                               model.output)[-1]
                TCO = TCO.copy()
                TCO[live] = new
            if role == "coarse":
                TCO_coarse = TCO
        spent = time.perf_counter() - t0 - (clock.seconds["render"] + clock.seconds["networks"] - before)
        clock.seconds["crops"] += spent
        if hypotheses is not None:
            hypotheses = hypotheses.copy()
            hypotheses[np.arange(N), pick] = TCO
            hypotheses = iterate_np.orthonormalise(hypotheses.reshape(-1, 4, 4)).reshape(hypotheses.shape)
        return iterate_np.orthonormalise(TCO_coarse), iterate_np.orthonormalise(TCO), hypotheses

    def _choose_candidate_np(self, candidates: np.ndarray, image: np.ndarray, K_b: np.ndarray, ids: list[int],
                             points: np.ndarray, renderer: Any,
                             clock: _Clock) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """:meth:`_choose_candidate` with numpy networks and ``image [H,W,3]``."""
        N, k = candidates.shape[:2]
        flat = candidates.reshape(N * k, 4, 4)
        owner = np.repeat(np.arange(N), k)
        refined, score = flat.copy(), np.full(N * k, -1.0)
        live = np.flatnonzero(iterate_np.valid_poses(flat))
        if len(live):
            assert self.refiner is not None
            net = _timed_numpy_net(self._nets["refiner"].run, clock)  # type: ignore[union-attr]
            own = owner[live]
            refined[live], score[live] = iterate_np.refine_and_score(
                net, image, K_b[own], flat[live], [ids[i] for i in own], points[own], renderer,
                self.refiner.crop_resolution, self.batch_size)
        pick = score.reshape(N, k).argmax(axis=1)
        refined = refined.reshape(N, k, 4, 4)
        return candidates[np.arange(N), pick], refined[np.arange(N), pick], refined, pick

    def _icp(self, TCO: Tensor, K: Tensor, depth: np.ndarray, det: Detections,
             size: tuple[int, int]) -> tuple[Tensor, list[IcpResult]]:
        from cosy_lite.inference.icp import refine_poses_icp

        depth, masks = self._icp_inputs(depth, det, size)
        ok = valid_poses(TCO)
        results: list[IcpResult | None] = [None] * len(TCO)
        idx = ok.nonzero().flatten().tolist()
        if idx:
            ids = det.obj_ids.tolist()
            syms = None if self.icp_symmetries is None else [self.icp_symmetries.get(ids[i]) for i in idx]
            out = refine_poses_icp(TCO[idx].numpy(), K.numpy(), depth, masks[idx], self.renderer,
                                   [ids[i] for i in idx], self.icp_config, syms)
            for i, r in zip(idx, out):
                results[i] = r
        for i in range(len(TCO)):
            if results[i] is None:
                results[i] = IcpResult(TCO[i].numpy().copy(), False, "invalid pose before ICP")
        TCO_new = torch.from_numpy(np.stack([r.TCO for r in results])).double()
        return orthonormalise(TCO_new), results  # type: ignore[return-value]

    def _icp_inputs(self, depth: np.ndarray, det: Detections, size: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
        """(depth [H,W] float32 m, masks [N,H,W] bool: the detections' masks, or their boxes)."""
        depth = np.asarray(depth, dtype=np.float32)
        if depth.shape != size:
            raise ValueError(f"depth must be [H,W] = {size} (as rgb), in metres; got {depth.shape}")
        if det.masks is not None:
            return depth, det.masks.cpu().numpy().astype(bool)
        if not self._warned_box_masks:
            warnings.warn("Predictor: detections without masks; ICP uses the detection boxes as masks",
                          RuntimeWarning, stacklevel=4)
            self._warned_box_masks = True
        return depth, _box_masks(det.boxes, size)

    def _icp_hypotheses(self, hypotheses: Tensor, K: Tensor, depth: np.ndarray, det: Detections,
                        size: tuple[int, int]) -> tuple[Tensor, list[IcpResult]]:
        """ICP of every hypothesis ``[N,k,4,4]``; per detection the result whose depth agrees best
        with the measured depth (:attr:`IcpResult.agreement`, :func:`~cosy_lite.inference.icp.depth_agreement`)."""
        N, k = hypotheses.shape[:2]
        flat_det = det.select(torch.arange(N).repeat_interleave(k))
        refined, results = self._icp(hypotheses.reshape(N * k, 4, 4).double(), K, depth, flat_det, size)
        agreement = np.array([r.agreement for r in results]).reshape(N, k)
        best = torch.from_numpy(agreement.argmax(axis=1) + np.arange(N) * k)
        return refined[best], [results[i] for i in best.tolist()]

    @staticmethod
    def _timings(clock: _Clock, t_start: float) -> dict[str, float]:
        out = {k: float(clock.seconds.get(k, 0.0)) for k in TIMING_KEYS}
        out["total"] = time.perf_counter() - t_start
        return out
