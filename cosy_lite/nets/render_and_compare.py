"""One render-and-compare iteration, shared by training, inference and validation.

Per item: crop box from the current pose (projected model points, centred on the projected origin,
4:3, margin 1.4), the image crop (``roi_align``) and its ``K_crop``, the object rendered alone at
the current pose with ``K_crop``, the 6-channel input (crop, rendering) -> network -> update.
The network itself stays tensor in / tensor out. Two kinds of output (``output``):

* ``"delta"``: the 9 numbers of the image-space update (:class:`~cosy_lite.nets.pose_net.PoseNet`,
  :class:`~cosy_lite.nets.siamese_pose_net.SiamesePoseNet`), applied by
  :func:`~cosy_lite.nets.pose_update.apply_pose_update`;
* ``"flow"``: a displacement field of the rendering's cells
  (:class:`~cosy_lite.nets.flow_pose_net.FlowPoseNet`), turned into a pose with the rendering's
  depth by :func:`~cosy_lite.nets.flow_pose_solver.pose_from_flow`.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, Sequence, cast

import torch
from torch import Tensor

from cosy_lite.geometry.crops import crop_boxes, crop_images, crop_intrinsics
from cosy_lite.geometry.pose_checks import valid_poses
from cosy_lite.nets.pose_update import apply_pose_update
from cosy_lite.render.renderer import Renderer

Size = tuple[int, int]


@dataclass
class NetInputs:
    """images [B,6,h,w] float in [0,1] (image crop, rendering); K_crop [B,3,3]; boxes [B,4] xyxy px;
    depth [B,1,h,w] (m, 0 off the object) of the rendering."""

    images: Tensor
    K_crop: Tensor
    boxes: Tensor
    depth: Tensor


OUTPUTS = ("delta", "flow")


@dataclass(frozen=True)
class FineCrops:
    """Refiner iterations run on larger crops than the network was trained on, keeping their input's depth.

    A flow refiner trained on 144x192 crops and run on 240x320 ones sees the object 1.67x larger: its
    stride-8 cells resolve finer rotation and image position, but its depth (the flow's scale) comes out
    biased (bench/RESULTS.md, session 28). So a fine iteration keeps the depth of its input pose along
    its new line of sight, and the iterations at the network's own size set the depth.

    resolution: (h, w) px of the fine crops (multiples of 16); iterations: 1-based numbers of the
    iterations run on them.
    """

    resolution: Size
    iterations: frozenset[int]

    @classmethod
    def of(cls, iterations: Sequence[int], resolution: Sequence[int]) -> FineCrops | None:
        """From the settings' lists (``InferenceConfig.refiner_fine_iterations`` / ``_resolution``); None
        without iterations."""
        if not iterations:
            return None
        h, w = (int(v) for v in resolution)
        return cls((h, w), frozenset(int(i) for i in iterations))


def keep_depth(TCO_in: Tensor, TCO_out: Tensor) -> Tensor:
    """``TCO_out`` with its translation scaled to the depth (camera z) of ``TCO_in``: the object stays
    on the same pixel, at the input's distance. Poses the update left invalid (z not > 0 or not
    finite) are returned as they are, for the loop's validity check to stop."""
    z_out = TCO_out[:, 2, 3]
    ok = torch.isfinite(z_out) & (z_out > 0)
    scale = torch.where(ok, TCO_in[:, 2, 3].to(z_out.dtype) / torch.where(ok, z_out, torch.ones_like(z_out)),
                        torch.ones_like(z_out))
    out = TCO_out.clone()
    out[:, :3, 3] = out[:, :3, 3] * scale.unsqueeze(1)
    return out


def network_output(net: object) -> str:
    """``"flow"`` for a flow network (its class says ``output = "flow"``), else ``"delta"``."""
    return getattr(net, "output", "delta")


def make_inputs(images: Tensor, K: Tensor, TCO: Tensor, obj_ids: Sequence[int], points: Tensor,
                renderer: Renderer, crop_resolution: Size,
                crop_transform: Callable[[Tensor, Tensor], Tensor] | None = None) -> NetInputs:
    """Network inputs for objects at poses ``TCO [B,4,4]`` (m) in ``images [B,3,H,W]`` (float, [0,1]).

    ``K [B,3,3]`` full-image intrinsics; ``points [B,N,3]`` model points (m) that set the crop size.
    ``crop_transform(crops, boxes)`` (training augmentation) is applied to the image crops only.
    """
    TCO = TCO.detach()
    boxes = crop_boxes(TCO, K, points, crop_resolution=crop_resolution)
    crops = crop_images(images, boxes, crop_resolution)
    if crop_transform is not None:
        crops = crop_transform(crops, boxes)
    K_crop = crop_intrinsics(K, boxes, crop_resolution)
    rendered, depth = renderer.render_tensors([int(i) for i in obj_ids], TCO.double().cpu().numpy(),
                                              K_crop.double().cpu().numpy(), cast(Size, tuple(crop_resolution)),
                                              device=images.device)
    assert rendered is not None  # rgb is rendered (depth_only=False)
    return NetInputs(torch.cat([crops, rendered.to(crops.dtype)], dim=1), K_crop, boxes, depth)


def updated_poses(TCO: Tensor, inp: NetInputs, out: Tensor, output: str = "delta") -> Tensor:
    """The poses ``TCO [B,4,4]`` after the network answered ``out`` to ``inp`` (see the module doc)."""
    if output == "flow":
        from cosy_lite.nets.flow_pose_solver import flow_stride, pose_from_flow

        return pose_from_flow(TCO, inp.K_crop, inp.depth, out, flow_stride(inp.depth, out)).to(TCO.dtype)
    if output != "delta":
        raise ValueError(f"output must be one of {OUTPUTS}, got {output!r}")
    return apply_pose_update(TCO, inp.K_crop, out.to(TCO.dtype))


def _by_batch(step: Callable[[slice], tuple[Tensor, ...]], n: int, batch_size: int) -> list[tuple[Tensor, ...]]:
    return [step(slice(s, s + batch_size)) for s in range(0, n, batch_size)]


def iterate_poses(net: Callable[[Tensor], Tensor], images: Tensor, K: Tensor, TCO_init: Tensor, obj_ids: Sequence[int],
                  points: Tensor, renderer: Renderer, n_iterations: int, crop_resolution: Size,
                  batch_size: int = 32, output: str | None = None, fine: FineCrops | None = None,
                  first_iteration: int = 1) -> list[Tensor]:
    """The render-and-compare loop: ``n_iterations`` updates from ``TCO_init [B,4,4]``; returns the
    poses after each iteration (``n_iterations`` tensors ``[B,4,4]``). ``fine``: the iterations run on
    larger crops, their input depth kept (:class:`FineCrops`), numbered from ``first_iteration``. ``net`` maps [b,6,h,w] ->
    [b,9] (``output="delta"``) or a flow field (``"flow"``); None: what ``net`` says
    (:func:`network_output`). Training validation, the torch predictor and the onnxruntime
    predictor all iterate here (:func:`iterate_poses_scored`).

    Invalid poses (:func:`~cosy_lite.geometry.pose_checks.valid_poses`: non-finite, not a rotation,
    behind the camera) are not rendered again: they keep their value through the remaining iterations.
    """
    return iterate_poses_scored(net, images, K, TCO_init, obj_ids, points, renderer, n_iterations, crop_resolution,
                                batch_size, output, fine, first_iteration)[0]


NOT_SCORED = -1.0  # the confidence of a pose that was not run (invalid), or of a network without one


def iterate_poses_scored(net: Callable[[Tensor], Tensor], images: Tensor, K: Tensor, TCO_init: Tensor,
                         obj_ids: Sequence[int], points: Tensor, renderer: Renderer, n_iterations: int,
                         crop_resolution: Size, batch_size: int = 32, output: str | None = None,
                         fine: FineCrops | None = None, first_iteration: int = 1) -> tuple[list[Tensor], Tensor]:
    """:func:`iterate_poses`, and the confidence ``[B]`` float64 of its last iteration: a flow network's mean
    confidence over the rendered cells at the pose that iteration started from
    (:func:`~cosy_lite.nets.flow_pose_solver.flow_confidence`; how well the rendering was recognised in the
    crop); :data:`NOT_SCORED` for a pose not run and for a network without confidence (``"delta"``)."""
    output = output or network_output(net)
    poses, TCO = [], TCO_init
    score = torch.full((len(TCO_init),), NOT_SCORED, dtype=torch.float64, device=TCO_init.device)
    last = first_iteration + n_iterations - 1
    for i in range(first_iteration, last + 1):
        is_fine = fine is not None and i in fine.iterations
        size = fine.resolution if fine is not None and is_fine else crop_resolution
        scored = output == "flow" and i == last  # (only the last iteration's confidence is returned)
        live = valid_poses(TCO).nonzero().flatten()
        if len(live) == len(TCO):
            new, score = _iterate_once(net, images, K, TCO, obj_ids, points, renderer, size, batch_size, output, scored)
            TCO = keep_depth(TCO, new) if is_fine else new
        elif len(live):
            new, score[live] = _iterate_once(net, images[live], K[live], TCO[live], [obj_ids[j] for j in live.tolist()],
                                             points[live], renderer, size, batch_size, output, scored)
            new = keep_depth(TCO[live], new) if is_fine else new
            TCO = TCO.clone()
            TCO[live] = new.to(TCO.dtype)
        poses.append(TCO)
    return poses, score


def _iterate_once(net: Callable[[Tensor], Tensor], images: Tensor, K: Tensor, TCO: Tensor, obj_ids: Sequence[int],
                  points: Tensor, renderer: Renderer, crop_resolution: Size, batch_size: int,
                  output: str, scored: bool = False) -> tuple[Tensor, Tensor]:
    """One update of every pose ``TCO [B,4,4]``, ``batch_size`` crops per network call, and with ``scored``
    (a flow network) each one's confidence ``[B]`` float64 (:func:`iterate_poses_scored`), else :data:`NOT_SCORED`."""
    from cosy_lite.nets.flow_pose_solver import flow_confidence, flow_stride

    def step(sl: slice) -> tuple[Tensor, Tensor]:
        inp = make_inputs(images[sl], K[sl], TCO[sl], obj_ids[sl], points[sl], renderer, crop_resolution)
        out = net(inp.images)
        score = (flow_confidence(inp.depth, out, flow_stride(inp.depth, out)) if scored else
                 torch.full((len(out),), NOT_SCORED, dtype=torch.float64, device=out.device))
        return updated_poses(TCO[sl], inp, out, output), score

    out = _by_batch(step, len(TCO), batch_size)
    if not out:
        return TCO, torch.zeros(0, dtype=torch.float64, device=TCO.device)
    return torch.cat([o[0] for o in out]), torch.cat([o[1] for o in out]).double().to(TCO.device)


def refine_and_score(net: Callable[[Tensor], Tensor], images: Tensor, K: Tensor, TCO: Tensor, obj_ids: Sequence[int],
                     points: Tensor, renderer: Renderer, crop_resolution: Size,
                     batch_size: int = 32) -> tuple[Tensor, Tensor]:
    """One iteration of a flow network from ``TCO [B,4,4]`` (arguments as :func:`iterate_poses`):
    (poses ``[B,4,4]``, confidence ``[B]`` float64, :func:`iterate_poses_scored`). Used to rank candidate
    start poses. Invalid poses are not run: they keep their value and score :data:`NOT_SCORED`."""
    poses, score = iterate_poses_scored(net, images, K, TCO, obj_ids, points, renderer, 1, crop_resolution,
                                        batch_size, "flow")
    return poses[0], score
