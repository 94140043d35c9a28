"""Batched renderer of objects alone on black: RGB, depth and mask of B crops (or full images) in
one call. Used by render-and-compare, ICP, the silhouette and appearance templates and the
pictures; its context is :mod:`.gl`'s. (The evaluator's depth windows are rasterised on the CPU:
:mod:`.depth_raster`.)

Conventions: ``TCO`` object-to-camera (m), OpenCV camera, ``K`` in pixels, ``resolution=(H, W)``.
Pixel ``(row r, column c)`` is sampled at ``(u, v) = (c + 0.5, r + 0.5)`` (as :mod:`.gl` and the
BOP toolkit). Depth is the camera z (m) of the visible surface, written by the fragment shader (no
depth-buffer decoding), 0 on the background. Colours are flat: texture x PBR base colour factor, or
vertex colours; ``shading="flat"`` (default) draws them as they are, ``"headlight"`` (what the pose
networks see) shades them by a light at the camera, ``ambient + (1 - ambient) |n . v|`` with face
normals from screen-space derivatives: without it an untextured object is a flat silhouette with no
3D shape inside. No anti-aliasing: a pixel is covered iff its centre is.

How it is fast (measured in ``bench/bench_render.py``): one headless GL context per renderer
(:class:`~cosy_lite.render.gl.EglContext`) and a minimal shader (no per-vertex normal matrix, no
lights); each mesh uploaded once as a vertex array (+ a mipmapped texture); back faces culled where
that cannot show (checked per mesh, see ``cull_back_faces``); the B crops of a call are drawn into
B framebuffers before any read-back, so on Mesa llvmpipe the rasterizer threads fill crop i while
this thread transforms crop i+1 (16k-face meshes make llvmpipe geometry-bound); each crop is then
read with one ``glReadPixels`` per channel straight into the ``[B,H,W]`` output arrays (no flip:
window y = v).
"""

from __future__ import annotations

import ctypes
import os
import threading
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, Iterator, Mapping, Protocol, Sequence

import numpy as np

from cosy_lite.render.gl import projection_matrices

if TYPE_CHECKING:
    import torch
    import trimesh

    from cosy_lite.bop.dataset import BopDataset
    from cosy_lite.render.gl import EglContext

Resolution = tuple[int, int]  # (H, W) pixels
CULL_CHECK_SIZE = 64  # px, side of the 14 views rendered to decide whether a mesh may be back-face culled
MAX_IN_FLIGHT_PIXELS = 1 << 22  # crops drawn before read-back hold at most this many pixels (12 B each)


@dataclass
class RenderOutput:
    """Renders of B items, each object alone on black.

    rgb: [B,H,W,3] uint8 (None when rendered depth-only); depth: [B,H,W] float32 metres, 0 =
    background; mask: [B,H,W] bool (depth > 0).
    """

    rgb: np.ndarray | None
    depth: np.ndarray
    mask: np.ndarray

    def to_tensors(self, device: torch.device | str = "cpu") -> tuple[torch.Tensor | None, torch.Tensor]:
        """rgb float32 [B,3,H,W] in [0, 1] (None if depth-only) and depth float32 [B,1,H,W] (m) on ``device``."""
        import torch

        depth = torch.from_numpy(self.depth).to(device).unsqueeze(1)
        if self.rgb is None:
            return None, depth
        rgb = torch.from_numpy(self.rgb).to(device).permute(0, 3, 1, 2).contiguous().float().div_(255.0)
        return rgb, depth


class Renderer(Protocol):
    """What training, inference and evaluation call; :class:`GlRenderer` is the backend."""

    def render(
        self, obj_ids: Sequence[int], TCO: Any, K: Any, resolution: Resolution, depth_only: bool = False
    ) -> RenderOutput:
        """obj_ids [B], TCO [B,4,4] (m, numpy or torch), K [B,3,3] or [3,3], resolution (H, W)."""
        ...

    def render_tensors(
        self, obj_ids: Sequence[int], TCO: Any, K: Any, resolution: Resolution,
        device: torch.device | str = "cpu", depth_only: bool = False,
    ) -> tuple[torch.Tensor | None, torch.Tensor]:
        """As :meth:`render`, as torch tensors: rgb [B,3,H,W] in [0, 1], depth [B,1,H,W] (m)."""
        ...


class MeshRenderer(Renderer, Protocol):
    """A renderer that also hands out its meshes (ICP's model clouds, textured-object checks)."""

    def mesh(self, obj_id: int) -> trimesh.Trimesh:
        """The mesh of ``obj_id`` (m)."""
        ...


# ----------------------------------------------------------------------------- inputs


def _as_numpy(x: Any) -> np.ndarray:
    if hasattr(x, "detach"):  # torch tensor, on any device
        x = x.detach().cpu().numpy()
    return np.asarray(x, dtype=np.float64)


def check_render_inputs(
    obj_ids: Sequence[int], TCO: Any, K: Any, resolution: Resolution
) -> tuple[list[int], np.ndarray, np.ndarray, Resolution]:
    """Validate and normalise render arguments.

    Returns: obj_ids as ints [B], TCO float64 [B,4,4], K float64 [B,3,3] (broadcast from [3,3]), (H, W).
    Raises ValueError naming the argument, its shape, and the batch index of a non-finite pose.
    """
    ids = [int(i) for i in obj_ids]
    B = len(ids)
    TCO = _as_numpy(TCO)
    if TCO.shape != (B, 4, 4):
        raise ValueError(f"TCO must be [B,4,4] with B = len(obj_ids) = {B}, got shape {TCO.shape}")
    K = _as_numpy(K)
    if K.shape == (3, 3):
        K = np.broadcast_to(K, (B, 3, 3))
    elif K.shape != (B, 3, 3):
        raise ValueError(f"K must be [3,3] or [B,3,3] with B = {B}, got shape {K.shape}")
    bad = np.flatnonzero(~np.isfinite(TCO).all(axis=(1, 2)))
    if len(bad):
        raise ValueError(f"TCO has NaN/inf at batch index {bad.tolist()}")
    bad = np.flatnonzero(~np.isfinite(K).all(axis=(1, 2)) | (K[:, 0, 0] <= 0) | (K[:, 1, 1] <= 0))
    if len(bad):
        raise ValueError(f"K is not finite with fx, fy > 0 at batch index {bad.tolist()}")
    if len(resolution) != 2 or int(resolution[0]) <= 0 or int(resolution[1]) <= 0:
        raise ValueError(f"resolution must be (H, W) > 0, got {resolution}")
    return ids, TCO, K, (int(resolution[0]), int(resolution[1]))


# ----------------------------------------------------------------------------- meshes -> GL arrays


@dataclass
class MeshArrays:
    """What is uploaded for one mesh: vertices [N,3] float32 (m), faces [F,3] uint32, and either
    uv [N,2] float32 + texture [h,w,4] uint8 (row 0 = image top) or colors [N,4] uint8."""

    vertices: np.ndarray
    faces: np.ndarray
    uv: np.ndarray | None = None
    texture: np.ndarray | None = None
    colors: np.ndarray | None = None


def _texture_image(material: Any) -> tuple[Any, np.ndarray]:
    """(PIL image or None, RGBA factor [4] in [0, 1]) of a trimesh material."""
    image = getattr(material, "baseColorTexture", None)
    factor = getattr(material, "baseColorFactor", None)  # PBRMaterial only; SimpleMaterial's diffuse is a lighting term
    if image is None:
        image = getattr(material, "image", None)
    factor = np.ones(4) if factor is None else np.asarray(factor, dtype=np.float64).reshape(-1)[:4]
    if factor.max() > 1.0:
        factor = factor / 255.0
    return image, factor


def mesh_arrays(mesh: trimesh.Trimesh) -> MeshArrays:
    """GL arrays of a trimesh: its texture when it has one, else vertex (or face) colours, else its main colour."""
    import trimesh

    vertices = np.asarray(mesh.vertices, dtype=np.float32)
    faces = np.asarray(mesh.faces, dtype=np.uint32)
    visual = mesh.visual
    assert visual is not None  # a Trimesh's visual setter replaces None by ColorVisuals()
    if isinstance(visual, trimesh.visual.TextureVisuals):
        image, factor = _texture_image(visual.material)
        if image is not None and visual.uv is not None:
            tex = np.asarray(image.convert("RGBA"), dtype=np.float64) * factor
            tex = np.clip(np.round(tex), 0, 255).astype(np.uint8)
            return MeshArrays(vertices, faces, uv=np.asarray(visual.uv, dtype=np.float32), texture=tex)
        colors = visual.material.main_color  # no image or no UVs: the material's colour
    elif getattr(visual, "kind", None) == "face":
        colors = np.repeat(np.asarray(visual.face_colors), 3, axis=0)
        vertices = vertices[faces].reshape(-1, 3)
        faces = np.arange(len(vertices), dtype=np.uint32).reshape(-1, 3)
    else:
        colors = visual.vertex_colors  # ColorVisuals: given colours, or trimesh's default grey
    colors = np.asarray(colors, dtype=np.uint8)
    if colors.ndim == 1:
        colors = np.broadcast_to(colors, (len(vertices), 4))
    return MeshArrays(vertices, faces, colors=np.ascontiguousarray(colors[:, :4]))


# ----------------------------------------------------------------------------- GL state

_VERTEX_SHADER = """#version 330 core
layout(location = 0) in vec3 position;
layout(location = 1) in vec4 uv_or_color;  // uv (textured) or rgba (vertex colours)
uniform mat4 MVP;    // clip <- object
uniform vec4 z_row;  // third row of TCO: camera z = dot(z_row, p)
uniform mat4 MV;     // camera <- object (TCO), for the shaded programs
out vec4 v_attribute;
out float v_z;
out vec3 v_position;  // camera frame
void main() {
    vec4 p = vec4(position, 1.0);
    gl_Position = MVP * p;
    v_attribute = uv_or_color;
    v_z = dot(z_row, p);
    v_position = (MV * p).xyz;
}
"""
# Headlight shading: a light at the camera, Lambertian, with the face normal from the screen-space
# derivatives of the camera-frame position (no normals uploaded); |n.v| so winding does not matter.
_SHADE = """
uniform float ambient;
vec4 shade(vec4 base) {
    vec3 n = normalize(cross(dFdx(v_position), dFdy(v_position)));
    float l = ambient + (1.0 - ambient) * abs(dot(n, normalize(v_position)));
    return vec4(base.rgb * l, base.a);
}
"""
_FRAGMENT_SHADERS = {
    "texture": """#version 330 core
in vec4 v_attribute; in float v_z;
uniform sampler2D color_texture;
layout(location = 0) out vec4 color;
layout(location = 1) out float depth;
void main() { color = texture(color_texture, v_attribute.xy); depth = v_z; }
""",
    "color": """#version 330 core
in vec4 v_attribute; in float v_z;
layout(location = 0) out vec4 color;
layout(location = 1) out float depth;
void main() { color = v_attribute; depth = v_z; }
""",
    "depth": """#version 330 core
in float v_z;
layout(location = 1) out float depth;
void main() { depth = v_z; }
""",
    "texture_lit": """#version 330 core
in vec4 v_attribute; in float v_z; in vec3 v_position;
uniform sampler2D color_texture;
layout(location = 0) out vec4 color;
layout(location = 1) out float depth;""" + _SHADE + """
void main() { color = shade(texture(color_texture, v_attribute.xy)); depth = v_z; }
""",
    "color_lit": """#version 330 core
in vec4 v_attribute; in float v_z; in vec3 v_position;
layout(location = 0) out vec4 color;
layout(location = 1) out float depth;""" + _SHADE + """
void main() { color = shade(v_attribute); depth = v_z; }
""",
}
SHADINGS = ("flat", "headlight")  # flat: the colours as they are; headlight: shaded (see _SHADE)
AMBIENT = 0.35  # share of the light that does not depend on the surface orientation (headlight)


@dataclass
class _GpuMesh:
    vao: int
    n_indices: int
    texture: int | None  # GL texture name, None for vertex colours
    buffers: list[int]
    cull: bool | None = None  # draw front faces only (see GlRenderer.cull_back_faces)


@dataclass
class _Framebuffer:
    """Colour (RGBA8) + depth (R32F) + depth-test (DEPTH24) renderbuffers of one H x W crop."""

    fbo: int
    renderbuffers: list[int]


@dataclass
class _GlState:
    context: EglContext
    programs: dict[str, int]
    uniforms: dict[str, tuple[int, int, int]]  # kind -> (MVP, z_row, MV) locations
    max_size: int  # largest framebuffer side (GL_MAX_RENDERBUFFER_SIZE, GL_MAX_VIEWPORT_DIMS)
    meshes: dict[int, _GpuMesh] = field(default_factory=dict)
    framebuffers: dict[Resolution, list[_Framebuffer]] = field(default_factory=dict)  # one per crop in flight


def _create_gl_state(device_index: int | None, load_torchvision: bool = True) -> _GlState:
    from cosy_lite.render.gl import EglContext

    context = EglContext(device_index, load_torchvision)  # first: selects EGL before PyOpenGL is imported
    from OpenGL import GL as gl
    from OpenGL.GL import shaders

    vs = shaders.compileShader(_VERTEX_SHADER, gl.GL_VERTEX_SHADER)
    programs = {
        kind: shaders.compileProgram(vs, shaders.compileShader(src, gl.GL_FRAGMENT_SHADER), validate=False)
        for kind, src in _FRAGMENT_SHADERS.items()
    }
    uniforms = {k: (gl.glGetUniformLocation(p, "MVP"), gl.glGetUniformLocation(p, "z_row"), gl.glGetUniformLocation(p, "MV"))
                for k, p in programs.items()}
    for kind in ("texture", "texture_lit"):
        gl.glUseProgram(programs[kind])
        gl.glUniform1i(gl.glGetUniformLocation(programs[kind], "color_texture"), 0)
    for kind in ("texture_lit", "color_lit"):
        gl.glUseProgram(programs[kind])
        gl.glUniform1f(gl.glGetUniformLocation(programs[kind], "ambient"), AMBIENT)
    gl.glEnable(gl.GL_DEPTH_TEST)
    gl.glDepthFunc(gl.GL_LESS)
    gl.glFrontFace(gl.GL_CW)  # window y = v mirrors the image: outward CCW faces appear clockwise
    gl.glDisable(gl.GL_BLEND)
    gl.glDisable(gl.GL_MULTISAMPLE)
    gl.glEnable(gl.GL_SCISSOR_TEST)
    gl.glClearColor(0.0, 0.0, 0.0, 0.0)
    gl.glPixelStorei(gl.GL_PACK_ALIGNMENT, 1)
    gl.glPixelStorei(gl.GL_UNPACK_ALIGNMENT, 1)
    gl.glActiveTexture(gl.GL_TEXTURE0)
    viewport = [int(v) for v in gl.glGetIntegerv(gl.GL_MAX_VIEWPORT_DIMS)]
    max_size = min(int(gl.glGetIntegerv(gl.GL_MAX_RENDERBUFFER_SIZE)), *viewport)
    return _GlState(context, programs, uniforms, max_size)


def _upload_mesh(arrays: MeshArrays) -> _GpuMesh:
    from OpenGL import GL as gl

    vao = gl.glGenVertexArrays(1)
    gl.glBindVertexArray(vao)
    vbo, ebo = gl.glGenBuffers(2)
    gl.glBindBuffer(gl.GL_ARRAY_BUFFER, vbo)
    data: np.ndarray  # [N,5] float32 (position, uv) or [N] records (position, colour)
    if arrays.texture is not None:
        assert arrays.uv is not None  # mesh_arrays gives uv with a texture
        data = np.ascontiguousarray(np.hstack([arrays.vertices, arrays.uv]), dtype=np.float32)
        attribute = (2, gl.GL_FLOAT, False, 20)
    else:
        data = np.zeros(len(arrays.vertices), dtype=[("p", "<f4", 3), ("c", "u1", 4)])
        data["p"], data["c"] = arrays.vertices, arrays.colors
        attribute = (4, gl.GL_UNSIGNED_BYTE, True, 16)
    stride = attribute[3]
    gl.glBufferData(gl.GL_ARRAY_BUFFER, data.nbytes, data, gl.GL_STATIC_DRAW)
    gl.glEnableVertexAttribArray(0)
    gl.glVertexAttribPointer(0, 3, gl.GL_FLOAT, False, stride, ctypes.c_void_p(0))
    gl.glEnableVertexAttribArray(1)
    gl.glVertexAttribPointer(1, attribute[0], attribute[1], attribute[2], stride, ctypes.c_void_p(12))
    faces = np.ascontiguousarray(arrays.faces, dtype=np.uint32)
    gl.glBindBuffer(gl.GL_ELEMENT_ARRAY_BUFFER, ebo)
    gl.glBufferData(gl.GL_ELEMENT_ARRAY_BUFFER, faces.nbytes, faces, gl.GL_STATIC_DRAW)
    gl.glBindVertexArray(0)
    texture = None
    if arrays.texture is not None:
        texture = gl.glGenTextures(1)
        gl.glBindTexture(gl.GL_TEXTURE_2D, texture)
        tex = np.ascontiguousarray(arrays.texture[::-1])  # GL rows start at v = 0, the image's bottom row
        h, w = tex.shape[:2]
        gl.glTexImage2D(gl.GL_TEXTURE_2D, 0, gl.GL_RGBA8, w, h, 0, gl.GL_RGBA, gl.GL_UNSIGNED_BYTE, tex)
        gl.glGenerateMipmap(gl.GL_TEXTURE_2D)
        # bilinear in the nearest mipmap level: ~10 % faster than trilinear on llvmpipe, alike to the eye
        gl.glTexParameteri(gl.GL_TEXTURE_2D, gl.GL_TEXTURE_MIN_FILTER, gl.GL_LINEAR_MIPMAP_NEAREST)
        gl.glTexParameteri(gl.GL_TEXTURE_2D, gl.GL_TEXTURE_MAG_FILTER, gl.GL_LINEAR)
    return _GpuMesh(vao, faces.size, texture, [vbo, ebo])


def _create_framebuffer(width: int, height: int) -> _Framebuffer:
    from OpenGL import GL as gl

    fbo = gl.glGenFramebuffers(1)
    gl.glBindFramebuffer(gl.GL_FRAMEBUFFER, fbo)
    rbs = [int(r) for r in gl.glGenRenderbuffers(3)]
    attachments = [
        (gl.GL_COLOR_ATTACHMENT0, gl.GL_RGBA8),
        (gl.GL_COLOR_ATTACHMENT1, gl.GL_R32F),
        (gl.GL_DEPTH_ATTACHMENT, gl.GL_DEPTH_COMPONENT24),
    ]
    for rb, (attachment, fmt) in zip(rbs, attachments):
        gl.glBindRenderbuffer(gl.GL_RENDERBUFFER, rb)
        gl.glRenderbufferStorage(gl.GL_RENDERBUFFER, fmt, width, height)
        gl.glFramebufferRenderbuffer(gl.GL_FRAMEBUFFER, attachment, gl.GL_RENDERBUFFER, rb)
    status = gl.glCheckFramebufferStatus(gl.GL_FRAMEBUFFER)
    if status != gl.GL_FRAMEBUFFER_COMPLETE:
        raise RuntimeError(f"framebuffer {width}x{height} incomplete (status {status:#x})")
    return _Framebuffer(fbo, rbs)


# ----------------------------------------------------------------------------- the backend


class GlRenderer:
    """The :class:`Renderer` backend: an :class:`~cosy_lite.render.gl.EglContext` (Mesa llvmpipe on
    CPU, NVIDIA EGL on a GPU) and a lean OpenGL pass of its own (see the module docstring for the
    conventions).

    Args:
        meshes: obj_id -> trimesh.Trimesh in metres (texture or vertex colours used as they are).
        models_dir: a BOP ``models/`` folder (``obj_XXXXXX.ply`` in mm, read with
            :func:`cosy_lite.bop.io.load_model`); used for ids not in ``meshes``.
        znear, zfar: clipping distances (m); surfaces outside are not drawn.
        max_in_flight: most crops drawn before their read-back (one framebuffer each, kept per
            resolution; also at most :data:`MAX_IN_FLIGHT_PIXELS` pixels, 48 MiB); larger batches
            are drawn and read back in groups.
        cull_back_faces: draw front faces only (about 2x faster on llvmpipe, where the 16k-face
            meshes make rendering geometry-bound). None (default): decided per mesh on upload, by
            rendering it from 14 directions with and without culling and culling only if the depth
            maps agree (closed meshes wound outward, up to 0.1 % of the pixels); a mesh with holes
            or flipped faces is drawn two-sided.
        device_index: EGL device; default ``$EGL_DEVICE_ID`` or 0.

    Meshes are read and uploaded lazily, once, on first use of an obj_id. The GL context is created
    on the first render, in the process and thread that renders: nothing happens at construction,
    so a renderer can be built in a parent and used in DataLoader workers (it pickles without its
    GL state; each process gets its own context). A forked child must not inherit a used context
    (Mesa hangs): with fork-started workers, do not render in the parent first, or use ``spawn``.
    Thread safety: calls are serialised by a lock; the context is made current in the calling
    thread for the duration of a call and released after, so any thread may call, one at a time.
    """

    def __init__(
        self,
        meshes: Mapping[int, trimesh.Trimesh] | None = None,
        models_dir: str | Path | None = None,
        znear: float = 0.01,
        zfar: float = 10.0,
        max_in_flight: int = 64,
        cull_back_faces: bool | None = None,
        device_index: int | None = None,
        shading: str = "flat",
        load_torchvision: bool = True,
    ):
        if meshes is None and models_dir is None:
            raise ValueError("GlRenderer needs meshes or a models_dir")
        if shading not in SHADINGS:
            raise ValueError(f"shading must be one of {SHADINGS}, got {shading!r}")
        self.shading = shading
        if not 0 < znear < zfar:
            raise ValueError(f"need 0 < znear < zfar, got znear={znear}, zfar={zfar}")
        self.meshes: dict[int, trimesh.Trimesh] = {int(k): v for k, v in (meshes or {}).items()}
        self.models_dir = None if models_dir is None else Path(models_dir)
        self.znear, self.zfar = float(znear), float(zfar)
        self.max_in_flight = int(max_in_flight)
        self.cull_back_faces = cull_back_faces
        self.device_index = device_index
        self.load_torchvision = load_torchvision
        self._gl: _GlState | None = None
        self._lock = threading.Lock()

    @classmethod
    def from_dataset(cls, dataset: BopDataset, eval_models: bool = False, **kwargs: Any) -> GlRenderer:
        """Renderer of a BOP dataset's ``models/`` (``eval_models``: ``models_eval/``, geometry only)."""
        return cls(models_dir=dataset.models_eval_dir if eval_models else dataset.models_dir, **kwargs)

    # ------------------------------------------------------------------ meshes
    def known_obj_ids(self) -> list[int]:
        """Ids given as meshes plus those with an ``obj_XXXXXX.ply`` in ``models_dir``."""
        ids = set(self.meshes)
        if self.models_dir is not None and self.models_dir.is_dir():
            for p in self.models_dir.glob("obj_*.ply"):
                if p.stem[4:].isdigit():
                    ids.add(int(p.stem[4:]))
        return sorted(ids)

    def mesh(self, obj_id: int) -> trimesh.Trimesh:
        """The mesh of ``obj_id`` (m), read from ``models_dir`` on first use. KeyError if unknown."""
        if obj_id not in self.meshes:
            path = None if self.models_dir is None else self.models_dir / f"obj_{obj_id:06d}.ply"
            if path is None or not path.is_file():
                where = "" if self.models_dir is None else f" (no {path})"
                raise KeyError(f"unknown obj_id {obj_id}{where}; known: {self.known_obj_ids()}")
            from cosy_lite.bop.io import load_model

            self.meshes[obj_id] = load_model(path)
        return self.meshes[obj_id]

    # ------------------------------------------------------------------ rendering
    def render(
        self, obj_ids: Sequence[int], TCO: Any, K: Any, resolution: Resolution, depth_only: bool = False
    ) -> RenderOutput:
        """Render each ``obj_ids[i]`` alone at ``TCO[i]`` seen by ``K[i]``.

        Args:
            obj_ids: [B]; TCO: [B,4,4] object-to-camera (m, numpy or torch); K: [B,3,3] or [3,3];
            resolution: (H, W); depth_only: skip colour (faster), ``rgb`` is then None.
        Items whose origin is not in front of the camera (TCO z <= 0) come out empty.
        """
        ids, TCO, K, (H, W) = check_render_inputs(obj_ids, TCO, K, resolution)
        for obj_id in dict.fromkeys(ids):
            self.mesh(obj_id)  # unknown ids fail before any GL work
        B = len(ids)
        rgb = None if depth_only else np.empty((B, H, W, 3), dtype=np.uint8)
        depth = np.empty((B, H, W), dtype=np.float32)
        if B == 0:
            return RenderOutput(rgb, depth, depth > 0)
        MVP = (projection_matrices(K, (H, W), self.znear, self.zfar) @ TCO).astype(np.float32)
        z_rows = np.ascontiguousarray(TCO[:, 2, :], dtype=np.float32)
        MV = np.ascontiguousarray(TCO, dtype=np.float32)
        with self._gl_current() as gls:
            meshes = {obj_id: self._gpu_mesh(gls, obj_id) for obj_id in dict.fromkeys(ids)}
            items = [meshes[obj_id] if TCO[i, 2, 3] > 0 else None for i, obj_id in enumerate(ids)]
            _check_size(gls, (H, W))
            group = max(1, min(self.max_in_flight, MAX_IN_FLIGHT_PIXELS // (H * W)))
            for i0 in range(0, B, group):
                sl = slice(i0, min(B, i0 + group))
                _render_pass(
                    gls, self._framebuffers(gls, (H, W), sl.stop - sl.start), items[sl], MVP[sl], z_rows[sl],
                    [m is not None and bool(m.cull) for m in items[sl]], (H, W),
                    None if rgb is None else rgb[sl], depth[sl], MV[sl], self.shading == "headlight",
                )
        return RenderOutput(rgb, depth, depth > 0)

    def render_tensors(
        self, obj_ids: Sequence[int], TCO: Any, K: Any, resolution: Resolution,
        device: torch.device | str = "cpu", depth_only: bool = False,
    ) -> tuple[torch.Tensor | None, torch.Tensor]:
        """:meth:`render` as tensors on ``device``: rgb float [B,3,H,W] in [0, 1] (None if
        depth_only), depth [B,1,H,W] (m)."""
        return self.render(obj_ids, TCO, K, resolution, depth_only).to_tensors(device)

    @contextmanager
    def _gl_current(self) -> Iterator[_GlState]:
        """This renderer's GL state, its context current in the calling thread, one caller at a time."""
        with self._lock:
            gls = self._current_gl_state()
            try:
                yield gls
            finally:
                gls.context.release()

    def _current_gl_state(self) -> _GlState:
        """This process's GL state, its context current in this thread (created on first use)."""
        if self._gl is not None and self._gl.context.pid != os.getpid():
            self._gl.context.destroy()  # inherited by fork: only forgets the parent's handles
            self._gl = None
        if self._gl is not None:
            try:
                self._gl.context.make_current()
                return self._gl
            except Exception:
                # The display was terminated under us (pyrender's OffscreenRenderer.delete() calls
                # eglTerminate, destroying every context of the process): start again.
                self._gl.context.destroy()
                self._gl = None
        self._gl = _create_gl_state(self.device_index, self.load_torchvision)  # current on creation; meshes re-uploaded lazily
        return self._gl

    def _gpu_mesh(self, gls: _GlState, obj_id: int) -> _GpuMesh:
        if obj_id not in gls.meshes:
            mesh = _upload_mesh(mesh_arrays(self.mesh(obj_id)))
            mesh.cull = self.cull_back_faces
            if mesh.cull is None:
                mesh.cull = self._culling_is_invisible(gls, mesh, np.asarray(self.mesh(obj_id).vertices))
            gls.meshes[obj_id] = mesh
        return gls.meshes[obj_id]

    def _culling_is_invisible(self, gls: _GlState, mesh: _GpuMesh, vertices: np.ndarray) -> bool:
        """True if dropping back faces changes no depth pixel (<= 0.1 %) in 14 views around the mesh:
        the mesh is closed and wound outward, so culling only skips hidden work."""
        from cosy_lite.geometry.transforms import look_at

        centre = (vertices.min(axis=0) + vertices.max(axis=0)) / 2.0
        radius = float(np.linalg.norm(vertices - centre, axis=1).max())
        dirs = np.concatenate([np.eye(3), -np.eye(3), np.array(np.meshgrid(*[[-1, 1]] * 3)).reshape(3, -1).T])
        dirs = dirs / np.linalg.norm(dirs, axis=1, keepdims=True)
        up = np.where(np.abs(dirs[:, 2:3]) > 0.9, [[0.0, 1.0, 0.0]], [[0.0, 0.0, 1.0]])
        TCO = np.stack([look_at(centre + 3.0 * radius * d, centre, u) for d, u in zip(dirs, up)])
        n, size = len(TCO), CULL_CHECK_SIZE
        K = np.array([[2.7 * size / 2, 0, size / 2], [0, 2.7 * size / 2, size / 2], [0, 0, 1]])
        MVP = projection_matrices(np.broadcast_to(K, (n, 3, 3)), (size, size), self.znear, self.zfar) @ TCO
        MVP, z_rows = MVP.astype(np.float32), np.ascontiguousarray(TCO[:, 2], dtype=np.float32)
        fbs = self._framebuffers(gls, (size, size), n)
        depths = [np.empty((n, size, size), dtype=np.float32) for _ in range(2)]
        for cull, depth in zip((False, True), depths):
            _render_pass(gls, fbs, [mesh] * n, MVP, z_rows, [cull] * n, (size, size), None, depth)
        changed = np.count_nonzero(depths[0] != depths[1])
        return bool(changed <= 0.001 * np.count_nonzero(depths[0]))

    @staticmethod
    def _framebuffers(gls: _GlState, resolution: Resolution, n: int) -> list[_Framebuffer]:
        """``n`` framebuffers of ``resolution`` (created on first need, kept for later calls)."""
        pool = gls.framebuffers.setdefault(resolution, [])
        while len(pool) < n:
            pool.append(_create_framebuffer(resolution[1], resolution[0]))
        return pool[:n]

    # ------------------------------------------------------------------ lifetime
    def close(self) -> None:
        """Free the GL context and everything in it (idempotent; the next render creates a new one)."""
        with self._lock:
            if self._gl is not None:
                self._gl.context.destroy()
                self._gl = None

    def __enter__(self) -> GlRenderer:
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()


    def __getstate__(self) -> dict[str, Any]:
        state = self.__dict__.copy()
        state["_gl"], state["_lock"] = None, None
        return state

    def __setstate__(self, state: dict[str, Any]) -> None:
        self.__dict__.update(state)
        self._lock = threading.Lock()


def _check_size(gls: _GlState, resolution: Resolution) -> None:
    if max(resolution) > gls.max_size:
        raise ValueError(f"resolution {tuple(resolution)} exceeds this GL's largest framebuffer side {gls.max_size}")


def _render_pass(
    gls: _GlState, fbs: Sequence[_Framebuffer], meshes: Sequence[_GpuMesh | None], MVP: np.ndarray, z_rows: np.ndarray,
    cull: Sequence[bool], resolution: Resolution, rgb: np.ndarray | None, depth: np.ndarray,
    MV: np.ndarray | None = None, shaded: bool = False,
) -> None:
    """Draw item j (None: nothing) into framebuffer j, then read every framebuffer into rgb/depth [j].

    One framebuffer per item, all drawn before any read-back: switching framebuffers hands the
    finished item to llvmpipe's rasterizer threads while this thread prepares the next one, and each
    item is drawn at the same window coordinates as when rendered alone (results identical).
    """
    from OpenGL import GL as gl

    H, W = resolution
    draw_buffers = [gl.GL_NONE if rgb is None else gl.GL_COLOR_ATTACHMENT0, gl.GL_COLOR_ATTACHMENT1]
    gl.glViewport(0, 0, W, H)
    gl.glScissor(0, 0, W, H)
    program, culling = None, None
    for j, mesh in enumerate(meshes):
        gl.glBindFramebuffer(gl.GL_FRAMEBUFFER, fbs[j].fbo)
        gl.glDrawBuffers(2, draw_buffers)
        gl.glClear(gl.GL_COLOR_BUFFER_BIT | gl.GL_DEPTH_BUFFER_BIT)
        if mesh is None:
            continue
        kind = "depth" if rgb is None else ("color" if mesh.texture is None else "texture") + ("_lit" if shaded else "")
        if kind != program:
            gl.glUseProgram(gls.programs[kind])
            program = kind
        if cull[j] != culling:
            (gl.glEnable if cull[j] else gl.glDisable)(gl.GL_CULL_FACE)
            culling = cull[j]
        mvp_loc, z_loc, mv_loc = gls.uniforms[kind]
        gl.glUniformMatrix4fv(mvp_loc, 1, gl.GL_TRUE, MVP[j])
        gl.glUniform4fv(z_loc, 1, z_rows[j])
        if shaded and MV is not None:
            gl.glUniformMatrix4fv(mv_loc, 1, gl.GL_TRUE, MV[j])
        if mesh.texture is not None and rgb is not None:
            gl.glBindTexture(gl.GL_TEXTURE_2D, mesh.texture)
        gl.glBindVertexArray(mesh.vao)
        gl.glDrawElements(gl.GL_TRIANGLES, mesh.n_indices, gl.GL_UNSIGNED_INT, None)
    gl.glBindVertexArray(0)
    for j in range(len(meshes)):
        gl.glBindFramebuffer(gl.GL_FRAMEBUFFER, fbs[j].fbo)
        _read_into(gl.GL_COLOR_ATTACHMENT1, (0, 0, W, H), gl.GL_RED, gl.GL_FLOAT, depth[j])
        if rgb is not None:
            _read_into(gl.GL_COLOR_ATTACHMENT0, (0, 0, W, H), gl.GL_RGB, gl.GL_UNSIGNED_BYTE, rgb[j])


def _read_into(buffer: int, window: tuple[int, int, int, int], fmt: int, gl_type: int, out: np.ndarray) -> None:
    """glReadPixels of ``window`` (x0, y0, x1, y1) of ``buffer`` straight into the C-contiguous ``out``."""
    from OpenGL import GL as gl

    assert out.flags.c_contiguous
    x0, y0, x1, y1 = window
    gl.glReadBuffer(buffer)
    gl.glReadPixels(x0, y0, x1 - x0, y1 - y0, fmt, gl_type, out.ctypes.data)
