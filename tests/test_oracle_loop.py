"""Closed-loop oracle test of the render-and-compare chain (crop -> render -> network -> pose update),
in the one loop of both predictor backends (:func:`cosy_lite.nets.render_and_compare.iterate_poses`).

An analytic "network" (:class:`Oracle`) stands in for the coarse and the refiner net. Like a real
net it sees only the ``[B,6,h,w]`` input: the observed crop (channels 0-2) and the rendering at
the current pose (channels 3-5). It outputs the exact CosyPose update that takes the pose it
believes an instance has to the next pose of a fixed schedule (waypoints 12, 6, 3, 1.5 deg and a
few cm off GT, then GT), so every iteration applies a non-trivial update. What it needs it reads
from the pixels, with the conventions written here (nothing imported from cosy_lite):

* the observed image is a coordinate ramp (R = pixel column, G = pixel row, B constant; uint8
  is exact for images up to 256 px). A bilinear crop of a linear ramp is exact, so each crop
  pixel tells which image point it samples: the crop box and ``K_crop`` are read from the image;
* the crop box is checked against this file's statement of the crop rule (:func:`spec_crop_box`);
* the rendered half is checked against this file's rasterisation of the object at the believed
  pose under the ``K_crop`` read from the image (:func:`silhouette_mismatch`; the meshes are convex);
* the update is this file's inversion of the update rule (:func:`update_between`).

A failed check is recorded in ``Oracle.flags``. The chain is right when, after coarse + 4 refiner
iterations, every estimate is GT and nothing was flagged; each bug injected into the chain's crop
boxes, crop intrinsics or pose update (``test_injected_bug_is_caught``) must be caught.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass, field

import numpy as np
import pytest
import torch
from scipy.spatial import ConvexHull
from scipy.spatial.transform import Rotation

from cosy_lite.bop.detections import Detections
from cosy_lite.inference.predictor import Predictor

# torchvision before any rendering (see cosy_lite.inference.predictor)
from cosy_lite.inference.settings import InferenceConfig
from cosy_lite.nets import render_and_compare
from cosy_lite.weights.loaders import PoseModel

H, W = 192, 256  # image (px): at most 256 wide and high, so the uint8 ramp holds every pixel index
K = np.array([[262.0, 0.0, 128.4], [0.0, 255.0, 95.6], [0.0, 0.0, 1.0]])
CROP = (96, 128)  # (h, w) of the nets' input crops
RAMP_B = 77  # blue value of the ramp image: a crop pixel with another blue sampled outside the image
N_REFINER_ITERATIONS = 4

# What the oracle tolerates. Measured with the correct chain, both loops: crop boxes within 3e-5 px
# of the rule, ramp crops within 4e-5 px of a straight line; at most 1 rendered pixel per crop on the
# wrong side of the silhouette, its centre within EDGE_PX of the edge. Injected bugs: 1.7-7 px, 100s of pixels.
BOX_TOL_PX = 0.02  # crop box read from the ramp vs the crop rule, each side
RAMP_TOL_PX = 1e-3  # the ramp crop vs a straight line (a pure resample of the ramp)
EDGE_PX = 0.02  # pixel centres nearer than this to the silhouette edge may go either way
# The chain's final estimates vs GT. Measured (float32 poses): 4e-6 deg, 3e-5 mm.
ROT_TOL_DEG = 1e-3
TRANS_TOL_MM = 1e-3

# ----------------------------------------------------------------------------- the spec, stated here

MARGIN = 1.4  # crop half-extent: this times the farthest projected model point (CosyPose's lambda)
IDENTITY_6D = np.array([1.0, 0.0, 0.0, 0.0, 1.0, 0.0])  # 6D rotation: first two columns of R
Z_UP = np.array([[0.0, 1.0, 0.0], [0.0, 0.0, -1.0], [-1.0, 0.0, 0.0]])  # start: object z up in the image
EXTENT_PER_DIAMETER = 0.92  # start depth: the box's larger side spans this fraction of the diameter


def project(TCO: np.ndarray, K: np.ndarray, X: np.ndarray) -> np.ndarray:
    """``[N,2]`` image coordinates (px; pixel ``c`` covers ``[c, c+1)``) of points ``X [N,3]`` (m)
    of an object at ``TCO [4,4]`` seen with ``K [3,3]``."""
    p = (X @ TCO[:3, :3].T + TCO[:3, 3]) @ K.T
    return p[:, :2] / p[:, 2:]


def spec_crop_box(TCO: np.ndarray, K: np.ndarray, points: np.ndarray, crop: tuple[int, int]) -> np.ndarray:
    """The crop box ``[x1, y1, x2, y2]`` (px) of an object at ``TCO``: centred on the projected object
    origin, with the crop's aspect ``r = w / h``, half-width ``MARGIN * max(dx, r dy)`` where ``dx``,
    ``dy`` are the farthest horizontal / vertical distances of the projected ``points [N,3]``."""
    h, w = crop
    r = w / h
    centre = project(TCO, K, np.zeros((1, 3)))[0]
    dx, dy = np.abs(project(TCO, K, points) - centre).max(axis=0)
    half_w = MARGIN * max(dx, r * dy)
    half = np.array([half_w, half_w / r])
    return np.concatenate([centre - half, centre + half])


def start_pose(box: np.ndarray, K: np.ndarray, diameter: float) -> np.ndarray:
    """The coarse net's starting pose ``[4,4]`` from a detection box ``[x1, y1, x2, y2]`` (px):
    rotation :data:`Z_UP`; depth ``z = min(fx s / box_w, fy s / box_h)``, ``s = EXTENT_PER_DIAMETER d``;
    the box centre back-projected at ``z``."""
    f, c = np.array([K[0, 0], K[1, 1]]), K[:2, 2]
    z = (f * EXTENT_PER_DIAMETER * diameter / (box[2:] - box[:2])).min()
    TCO = np.eye(4)
    TCO[:3, :3] = Z_UP
    TCO[:3, 3] = [*(((box[:2] + box[2:]) / 2 - c) / f * z), z]
    return TCO


def crop_intrinsics(K: np.ndarray, box: np.ndarray, crop: tuple[int, int]) -> np.ndarray:
    """``K_crop [3,3]`` of the crop ``box`` resampled to ``crop`` (h, w): crop pixel ``j`` (centre
    ``u' = j + 0.5``) samples the image at ``u = x1 + (j + 0.5) s``, ``s = (x2 - x1) / w``; likewise v."""
    h, w = crop
    sx, sy = (box[2] - box[0]) / w, (box[3] - box[1]) / h
    A = np.array([[1 / sx, 0.0, -box[0] / sx], [0.0, 1 / sy, -box[1] / sy], [0.0, 0.0, 1.0]])
    return A @ K


def update_between(TCO: np.ndarray, target: np.ndarray, K_crop: np.ndarray) -> np.ndarray:
    """The 9 net outputs that take ``TCO [4,4]`` to ``target [4,4]``, inverting the CosyPose update:
    ``R_new = dR R`` (``dR`` from the 6D outputs plus :data:`IDENTITY_6D`), ``z_new = exp(o8) z``,
    ``xy_new / z_new = xy / z + (o6, o7) / (fx, fy)`` of ``K_crop`` (a shift in crop pixels)."""
    dR = target[:3, :3] @ TCO[:3, :3].T
    rot6d = np.concatenate([dR[:, 0], dR[:, 1]]) - IDENTITY_6D
    f = np.array([K_crop[0, 0], K_crop[1, 1]])
    vxvy = f * (target[:2, 3] / target[2, 3] - TCO[:2, 3] / TCO[2, 3])
    return np.concatenate([rot6d, vxvy, [np.log(target[2, 3] / TCO[2, 3])]])


def ramp_image() -> np.ndarray:
    """``[H,W,3]`` uint8: R = pixel column, G = pixel row, B = :data:`RAMP_B`."""
    rows, cols = np.mgrid[0:H, 0:W]
    return np.stack([cols, rows, np.full((H, W), RAMP_B)], axis=-1).astype(np.uint8)


def read_crop_box(observed: np.ndarray) -> tuple[np.ndarray, float, bool]:
    """(crop box ``[x1, y1, x2, y2]`` px, largest deviation from a straight ramp in px, whether every
    pixel sampled inside the image) of a crop ``[3,h,w]`` (in [0, 1]) of :func:`ramp_image`.

    The ramp's value at pixel ``c`` is ``c``, i.e. ``u - 0.5`` at the pixel centre, and bilinear
    resampling keeps a linear function exact: crop column ``j`` reads ``x1 + (j + 0.5) s - 0.5``."""
    h, w = observed.shape[1:]
    u = observed[0].astype(np.float64) * 255 + 0.5  # [h,w]: image u sampled by each crop pixel
    v = observed[1].astype(np.float64) * 255 + 0.5
    sx, x1 = np.polyfit(np.arange(w) + 0.5, u.mean(axis=0), 1)
    sy, y1 = np.polyfit(np.arange(h) + 0.5, v.mean(axis=1), 1)
    deviation = max(np.abs(u - (x1 + (np.arange(w) + 0.5) * sx)).max(),
                    np.abs(v - (y1 + (np.arange(h) + 0.5)[:, None] * sy)).max())
    inside = bool(np.abs(observed[2].astype(np.float64) * 255 - RAMP_B).max() < 1e-3)
    return np.array([x1, y1, x1 + w * sx, y1 + h * sy]), float(deviation), inside


def _cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """z of the cross product of 2D vectors ``[..., 2]``."""
    return a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0]


def silhouette_mismatch(mask: np.ndarray, uv: np.ndarray) -> int:
    """Pixels of ``mask [h,w]`` (the rendered object) that disagree with the convex hull of the
    projected mesh vertices ``uv [V,2]`` (a pixel is covered iff its centre is inside), not
    counting pixels whose centre lies within :data:`EDGE_PX` of a hull edge's line."""
    h, w = mask.shape
    hull = uv[ConvexHull(uv).vertices]
    a, edge = hull, np.roll(hull, -1, axis=0) - hull  # [E,2]
    orientation = np.sign(_cross(edge[0], edge[1]))
    centres = np.stack(np.meshgrid(np.arange(w) + 0.5, np.arange(h) + 0.5), axis=-1).reshape(-1, 1, 2)
    distance = orientation * _cross(edge, centres - a) / np.linalg.norm(edge, axis=1)  # [h*w,E], > 0 inside
    nearest = distance.min(axis=1).reshape(h, w)
    clear = np.abs(nearest) > EDGE_PX
    return int(((nearest > 0) != mask)[clear].sum())


# ----------------------------------------------------------------------------- the oracle


@dataclass
class Track:
    """One object instance as the oracle follows it. ``vertices [V,3]`` (m): its convex mesh;
    ``points [N,3]`` (m): the model points the crop rule uses; ``believed [4,4]``: the pose it
    believes the chain holds; ``targets``: where its calls send the instance, in order (last: GT);
    ``roles``: the net ("coarse" / "refiner") of each call so far."""

    obj_id: int
    vertices: np.ndarray
    points: np.ndarray
    believed: np.ndarray
    targets: list[np.ndarray]
    roles: list[str] = field(default_factory=list)


class Oracle:
    """The analytic net: ``[B,6,h,w]`` float32 in [0, 1] -> ``[B,9]`` float32 updates. Failed checks
    go to ``flags`` as (kind, message), kind one of "input", "crop", "render", "order"."""

    def __init__(self, K: np.ndarray, crop: tuple[int, int], tracks: list[Track]):
        self.K, self.crop, self.tracks = K, crop, tracks
        self.flags: list[tuple[str, str]] = []

    def flag(self, kind: str, message: str) -> None:
        self.flags.append((kind, message))

    def __call__(self, x: np.ndarray, role: str) -> np.ndarray:
        if x.ndim != 4 or x.shape[1:] != (6, *self.crop) or x.dtype != np.float32:
            self.flag("input", f"{role}: input {x.dtype} {x.shape}, expected float32 [B,6,{self.crop[0]},"
                               f"{self.crop[1]}]")
        return np.stack([self._answer(item, role) for item in x]).astype(np.float32)

    def _answer(self, item: np.ndarray, role: str) -> np.ndarray:
        box, deviation, inside = read_crop_box(item[:3])
        if deviation > RAMP_TOL_PX or not inside:
            self.flag("crop", f"{role}: the crop is no plain resample of the image inside it "
                              f"(ramp deviation {deviation:.2g} px, inside {inside})")
        track = self._track_of(box)
        expected = spec_crop_box(track.believed, self.K, track.points, self.crop)
        off = np.abs(box - expected).max()
        if off > BOX_TOL_PX:
            self.flag("crop", f"{role} obj {track.obj_id} call {len(track.roles)}: crop box {box.round(2)} "
                              f"vs the rule's {expected.round(2)} ({off:.3g} px off)")
        K_crop = crop_intrinsics(self.K, box, self.crop)
        mask = item[3:].max(axis=0) > 0
        wrong = silhouette_mismatch(mask, project(track.believed, K_crop, track.vertices))
        if wrong or not mask.any():
            self.flag("render", f"{role} obj {track.obj_id} call {len(track.roles)}: {wrong} pixels of the "
                                f"rendering ({int(mask.sum())} px) off the object's silhouette at the believed pose")
        expected_role = "coarse" if not track.roles else "refiner"
        if role != expected_role or len(track.roles) >= len(track.targets):
            self.flag("order", f"obj {track.obj_id}: call {len(track.roles)} by the {role} net "
                               f"(expected {expected_role}, {len(track.targets)} calls in all)")
        target = track.targets[min(len(track.roles), len(track.targets) - 1)]
        track.roles.append(role)
        delta = update_between(track.believed, target, K_crop)
        track.believed = target
        return delta

    def _track_of(self, box: np.ndarray) -> Track:
        """The instance whose believed projected origin is nearest the crop's centre."""
        centre = (box[:2] + box[2:]) / 2
        gaps = [np.linalg.norm(project(t.believed, self.K, np.zeros((1, 3)))[0] - centre) for t in self.tracks]
        return self.tracks[int(np.argmin(gaps))]


class OracleNet:
    """The oracle as the loop's net: a plain callable ``Tensor [B,6,h,w] -> [B,9]``, as an
    onnxruntime session is (not a torch module)."""

    def __init__(self, oracle: Oracle, role: str):
        self.oracle, self.role = oracle, role

    def __call__(self, x: torch.Tensor) -> torch.Tensor:
        return torch.from_numpy(self.oracle(x.detach().cpu().numpy(), self.role))


# ----------------------------------------------------------------------------- the scene


@dataclass
class Scene:
    """Two convex objects in the ramp image: ids [N], GT poses [N,4,4] (m), detection boxes [N,4]
    (px, float32 values: the projected vertices' boxes at GT), model points, renderer."""

    ids: list[int]
    TCO_gt: np.ndarray
    boxes: np.ndarray
    vertices: dict[int, np.ndarray]
    points: dict[int, np.ndarray]
    diameters: dict[int, float]
    objects: object
    renderer: object
    image: np.ndarray


# (axis, angle deg, translation m) of the waypoints before GT: R = Rot(axis, angle) R_gt, t = t_gt + dt
WAYPOINTS = [((0.3, 1.0, 0.2), 12.0, (0.006, -0.004, 0.03)), ((1.0, -0.4, 0.5), 6.0, (-0.003, 0.003, -0.015)),
             ((-0.2, 0.5, 1.0), 3.0, (0.002, 0.001, 0.008)), ((0.7, 0.7, -0.3), 1.5, (-0.001, -0.002, -0.004))]


def _targets(TCO_gt: np.ndarray) -> list[np.ndarray]:
    """The poses the oracle's calls send an instance to: one per waypoint, then GT."""
    out = []
    for axis, deg, dt in WAYPOINTS:
        T = TCO_gt.copy()
        rotvec = np.radians(deg) * np.array(axis) / np.linalg.norm(axis)
        T[:3, :3] = Rotation.from_rotvec(rotvec).as_matrix() @ T[:3, :3]
        T[:3, 3] += dt
        out.append(T)
    return out + [TCO_gt.copy()]


def make_scene() -> Scene:
    """Box (id 1) and cylinder (id 2) at GT poses 0.55-0.6 m away, their renderer, the ramp image."""
    import trimesh

    from cosy_lite.nets.object_table import ObjectTable
    from cosy_lite.render.renderer import GlRenderer

    rng = np.random.default_rng(0)
    meshes = {1: trimesh.creation.box(extents=(0.08, 0.05, 0.03)),
              2: trimesh.creation.cylinder(radius=0.025, height=0.09, sections=24)}
    vertices = {}
    for i, m in meshes.items():
        m.vertices = np.asarray(m.vertices, dtype=np.float32).astype(np.float64)  # what the tables hold
        m.visual.vertex_colors = rng.integers(40, 256, size=(len(m.vertices), 4)).astype(np.uint8)  # never black
        vertices[i] = np.asarray(m.vertices)
    ids = [1, 2]
    n = max(len(v) for v in vertices.values())
    points = {i: np.concatenate([v, np.repeat(v[:1], n - len(v), axis=0)]) for i, v in vertices.items()}
    diameters = {i: float(np.float32(np.linalg.norm(v[:, None] - v[None], axis=-1).max())) for i, v in vertices.items()}
    objects = ObjectTable(ids, torch.from_numpy(np.stack([points[i] for i in ids])).float(),
                          torch.eye(4)[None, None].repeat(2, 1, 1, 1), torch.ones(2, 1, dtype=torch.bool),
                          torch.tensor([diameters[i] for i in ids], dtype=torch.float32))
    TCO_gt = np.tile(np.eye(4), (2, 1, 1))
    TCO_gt[0, :3, :3] = Rotation.from_euler("xyz", [40, -25, 30], degrees=True).as_matrix()
    TCO_gt[1, :3, :3] = Rotation.from_euler("xyz", [-60, 15, 10], degrees=True).as_matrix()
    TCO_gt[:, :3, 3] = [[-0.07, 0.01, 0.55], [0.06, -0.015, 0.6]]
    boxes = np.stack([np.concatenate([uv.min(axis=0), uv.max(axis=0)])
                      for uv in (project(T, K, vertices[i]) for T, i in zip(TCO_gt, ids))])
    boxes = boxes.astype(np.float32).astype(np.float64)  # Detections hold float32
    renderer = GlRenderer(meshes=meshes)
    return Scene(ids, TCO_gt, boxes, vertices, points, diameters, objects, renderer, ramp_image())


@pytest.fixture(scope="module")
def scene() -> Scene:
    return make_scene()


def _run(scene: Scene) -> tuple[Oracle, np.ndarray, np.ndarray]:
    """(the oracle after one ``predict``, rotation errors [N] deg, translation errors [N] mm) of
    coarse + :data:`N_REFINER_ITERATIONS` refiner iterations from the GT boxes."""
    tracks = [Track(i, scene.vertices[i], scene.points[i], start_pose(box, K, scene.diameters[i]), _targets(T))
              for i, T, box in zip(scene.ids, scene.TCO_gt, scene.boxes)]
    oracle = Oracle(K, CROP, tracks)
    coarse, refiner = (PoseModel(OracleNet(oracle, role), role, CROP, scene.ids) for role in ("coarse", "refiner"))
    predictor = Predictor(coarse, refiner, scene.objects, scene.renderer,
                          config=InferenceConfig(n_refiner_iterations=N_REFINER_ITERATIONS))
    det = Detections(torch.from_numpy(scene.boxes).float(), torch.tensor(scene.ids), torch.tensor([0.9, 0.8]))
    est = predictor.predict(scene.image, K, detections=det)
    TCO = est.TCO.numpy()[[est.obj_ids.tolist().index(i) for i in scene.ids]]
    cos = (np.trace(TCO[:, :3, :3].transpose(0, 2, 1) @ scene.TCO_gt[:, :3, :3], axis1=1, axis2=2) - 1) / 2
    rot_deg = np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))
    trans_mm = np.linalg.norm(TCO[:, :3, 3] - scene.TCO_gt[:, :3, 3], axis=1) * 1000
    return oracle, rot_deg, trans_mm


# ----------------------------------------------------------------------------- tests


def test_oracle_closed_loop_reaches_gt(scene):
    oracle, rot_deg, trans_mm = _run(scene)
    print(f"rotation errors {rot_deg} deg, translation errors {trans_mm} mm, flags {oracle.flags}")
    assert oracle.flags == []
    assert [t.roles for t in oracle.tracks] == [["coarse"] + ["refiner"] * N_REFINER_ITERATIONS] * len(scene.ids)
    assert (rot_deg < ROT_TOL_DEG).all() and (trans_mm < TRANS_TOL_MM).all()


# ----------------------------------------------------------------------------- injected bugs


def _wider_margin(crop_boxes):
    return functools.partial(crop_boxes, margin=1.5)


def _shifted_centre(crop_boxes):
    def buggy(*args, **kwargs):
        boxes = crop_boxes(*args, **kwargs)
        boxes[:, 0::2] += 2.0  # 2 px to the right
        return boxes

    return buggy


def _shifted_pixels(crop_images):
    def buggy(images, boxes, *args, **kwargs):
        boxes = boxes.clone() if isinstance(boxes, torch.Tensor) else boxes.copy()
        boxes[:, 0::2] += 1.0  # the pixels cropped 1 px right of the box that K_crop describes
        return crop_images(images, boxes, *args, **kwargs)

    return buggy


def _shifted_cx(crop_intrinsics):
    def buggy(*args, **kwargs):
        K_crop = crop_intrinsics(*args, **kwargs)
        K_crop[:, 0, 2] += 2.0  # renders 2 px to the right of the crop
        return K_crop

    return buggy


def _swapped_vxvy(apply_pose_update):
    def buggy(TCO, K_crop, delta):
        return apply_pose_update(TCO, K_crop, delta[:, [0, 1, 2, 3, 4, 5, 7, 6, 8]])

    return buggy


def _rotation_on_the_right(apply_pose_update):
    def buggy(TCO, K_crop, delta):
        out = apply_pose_update(TCO, K_crop, delta)
        R = TCO[:, :3, :3]
        dR = out[:, :3, :3] @ R.swapaxes(1, 2)
        out[:, :3, :3] = R @ dR  # R_new = R dR instead of dR R
        return out

    return buggy


# name -> (function of the loop modules to replace, its buggy version from the original, flags expected,
# whether the final poses miss GT). Crop and K_crop bugs leave the chain self-consistent (the
# update uses the crop's own K_crop), so only the oracle's checks see them.
BUGS = {
    "crop_margin_1.5": ("crop_boxes", _wider_margin, {"crop"}, False),
    "crop_centre_+2px": ("crop_boxes", _shifted_centre, {"crop"}, False),
    "crop_pixels_+1px": ("crop_images", _shifted_pixels, {"crop", "render"}, False),
    "render_K_crop_cx_+2px": ("crop_intrinsics", _shifted_cx, {"render"}, False),
    "update_vx_vy_swapped": ("apply_pose_update", _swapped_vxvy, {"crop", "render"}, True),
    "update_rotation_on_the_right": ("apply_pose_update", _rotation_on_the_right, {"crop", "render"}, True),
}


@pytest.mark.parametrize("bug", sorted(BUGS))
def test_injected_bug_is_caught(scene, bug, monkeypatch):
    name, make_buggy, expected_flags, misses_gt = BUGS[bug]
    monkeypatch.setattr(render_and_compare, name, make_buggy(getattr(render_and_compare, name)))
    oracle, rot_deg, trans_mm = _run(scene)
    kinds = {kind for kind, _ in oracle.flags}
    print(f"{bug}: rotation errors {rot_deg} deg, translation errors {trans_mm} mm, "
          f"{len(oracle.flags)} flags {sorted(kinds)}: {oracle.flags[:2]}")
    assert kinds == expected_flags
    at_gt = (rot_deg < ROT_TOL_DEG).all() and (trans_mm < TRANS_TOL_MM).all()
    assert at_gt != misses_gt
    if misses_gt:
        assert max(rot_deg.max() / ROT_TOL_DEG, trans_mm.max() / TRANS_TOL_MM) > 100
