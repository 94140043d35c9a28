"""Depth of single objects inside image windows (EGL/OpenGL), for VSD.

Why a renderer of its own: VSD only needs the depth of one object at a time, and only where the
object is. This renderer keeps one OpenGL context, one framebuffer of the image size and one
vertex array per object; each render sets two matrices, clears and draws inside a *scissor*
window (the projected bounds of the object, see :func:`object_window`) and reads back only that
window. The projection is the full-image one, so the pixels inside the window are exactly those of
a full-image render (no principal-point shift, no resampling).

Conventions (as bop_toolkit's ``renderer_vispy``): OpenCV camera, window y = H - v so that the
pixel of row ``r``, column ``c`` is sampled at ``(u, v) = (c + 0.5, r + 0.5)``; depth = the camera
Z of the visible surface (m), 0 where the object is not rendered. The depth is written by the
fragment shader (interpolated eye Z, float32), not decoded from the depth buffer.
"""

from __future__ import annotations

import ctypes
from dataclasses import dataclass

import numpy as np

_VERTEX_SHADER = """
#version 330 core
layout(location = 0) in vec3 position;
uniform mat4 model_view;  // model -> OpenCV camera
uniform mat4 projection;  // OpenCV camera -> clip
out float cam_z;
void main() {
    vec4 p = model_view * vec4(position, 1.0);
    cam_z = p.z;
    gl_Position = projection * p;
}
"""

_FRAGMENT_SHADER = """
#version 330 core
in float cam_z;
layout(location = 0) out float depth;
void main() {
    depth = cam_z;
}
"""


@dataclass(frozen=True)
class Window:
    """Image window ``[x0, x1) x [y0, y1)`` in pixels (columns x, rows y)."""

    x0: int
    y0: int
    x1: int
    y1: int

    @property
    def empty(self) -> bool:
        return self.x1 <= self.x0 or self.y1 <= self.y0

    @property
    def shape(self) -> tuple[int, int]:
        return max(0, self.y1 - self.y0), max(0, self.x1 - self.x0)

    def union(self, other: Window) -> Window:
        if self.empty:
            return other
        if other.empty:
            return self
        return Window(min(self.x0, other.x0), min(self.y0, other.y0), max(self.x1, other.x1), max(self.y1, other.y1))


EMPTY_WINDOW = Window(0, 0, 0, 0)
NEAR_MIN_M = 1e-3  # nearest clipping plane allowed (m)


def object_window(pts: np.ndarray, TCO: np.ndarray, K: np.ndarray, width: int, height: int, margin: int = 2) -> Window:
    """Pixels that can be covered by an object: bounds of its projected points, plus ``margin``.

    Args:
        pts: [N,3] points whose convex hull contains the model (e.g. its hull vertices), m.
        TCO: [4,4] object-to-camera; K: [3,3]; width, height: image size (px).
    Returns:
        The window clipped to the image; the whole image if a point is closer than
        ``NEAR_MIN_M`` to the camera plane (its projection is unbounded); empty if all are behind.
    """
    p = pts @ TCO[:3, :3].T + TCO[:3, 3]
    z = p[:, 2]
    if np.all(z <= 0):
        return EMPTY_WINDOW
    if np.any(z < NEAR_MIN_M):
        return Window(0, 0, width, height)
    uv = (p @ np.asarray(K, dtype=np.float64).T)[:, :2] / z[:, None]
    # A pixel (c, r) is sampled at (c + 0.5, r + 0.5); triangles cover samples inside their projection.
    x0 = int(np.floor(uv[:, 0].min() - 0.5)) - margin
    x1 = int(np.ceil(uv[:, 0].max() - 0.5)) + margin + 1
    y0 = int(np.floor(uv[:, 1].min() - 0.5)) - margin
    y1 = int(np.ceil(uv[:, 1].max() - 0.5)) + margin + 1
    w = Window(max(0, x0), max(0, y0), min(width, x1), min(height, y1))
    return EMPTY_WINDOW if w.empty else w


def projection_matrix(K: np.ndarray, width: int, height: int, near: float, far: float) -> np.ndarray:
    """[4,4] OpenCV camera -> clip coordinates with window ``x = u``, ``y = H - v`` and NDC z in [-1, 1]."""
    fx, s, cx = K[0, 0], K[0, 1], K[0, 2]
    fy, cy = K[1, 1], K[1, 2]
    P = np.zeros((4, 4))
    P[0] = [2.0 * fx / width, 2.0 * s / width, 2.0 * cx / width - 1.0, 0.0]
    P[1] = [0.0, -2.0 * fy / height, 1.0 - 2.0 * cy / height, 0.0]
    P[2] = [0.0, 0.0, (far + near) / (far - near), -2.0 * far * near / (far - near)]
    P[3] = [0.0, 0.0, 1.0, 0.0]
    return P


class WindowDepthRenderer:
    """Depth of one object at a time, read back inside a window (see module docstring).

    Args:
        meshes: obj_id -> (vertices [N,3] m, faces [F,3] int); uploaded once.
        width, height: image size (px).
    Use as a context manager, or call :meth:`close`.
    """

    def __init__(self, meshes: dict[int, tuple[np.ndarray, np.ndarray]], width: int, height: int):
        from cosy_lite.render.gl import use_egl

        use_egl()
        from pyrender.platforms.egl import EGLPlatform

        self.width, self.height = int(width), int(height)
        self._platform = EGLPlatform(self.width, self.height)
        self._platform.init_context()
        self._platform.make_current()
        self._fbo = None
        self._gl_objects: dict[int, tuple[int, int, int, int]] = {}  # obj_id -> vao, vbo, ebo, n_indices
        self._corners: dict[int, np.ndarray] = {}  # obj_id -> [8,3] bounding box corners (m)
        try:
            self._setup()
            for obj_id, (vertices, faces) in meshes.items():
                self._upload(int(obj_id), vertices, faces)
        except Exception:
            self.close()
            raise

    # ------------------------------------------------------------------ GL set-up
    def _setup(self) -> None:
        from OpenGL import GL as gl
        from OpenGL.GL import shaders

        self._program = shaders.compileProgram(
            shaders.compileShader(_VERTEX_SHADER, gl.GL_VERTEX_SHADER),
            shaders.compileShader(_FRAGMENT_SHADER, gl.GL_FRAGMENT_SHADER),
        )
        self._loc_mv = gl.glGetUniformLocation(self._program, "model_view")
        self._loc_proj = gl.glGetUniformLocation(self._program, "projection")
        self._fbo = gl.glGenFramebuffers(1)
        gl.glBindFramebuffer(gl.GL_FRAMEBUFFER, self._fbo)
        self._color = gl.glGenRenderbuffers(1)
        gl.glBindRenderbuffer(gl.GL_RENDERBUFFER, self._color)
        gl.glRenderbufferStorage(gl.GL_RENDERBUFFER, gl.GL_R32F, self.width, self.height)
        gl.glFramebufferRenderbuffer(gl.GL_FRAMEBUFFER, gl.GL_COLOR_ATTACHMENT0, gl.GL_RENDERBUFFER, self._color)
        self._depth = gl.glGenRenderbuffers(1)
        gl.glBindRenderbuffer(gl.GL_RENDERBUFFER, self._depth)
        gl.glRenderbufferStorage(gl.GL_RENDERBUFFER, gl.GL_DEPTH_COMPONENT32F, self.width, self.height)
        gl.glFramebufferRenderbuffer(gl.GL_FRAMEBUFFER, gl.GL_DEPTH_ATTACHMENT, gl.GL_RENDERBUFFER, self._depth)
        status = gl.glCheckFramebufferStatus(gl.GL_FRAMEBUFFER)
        if status != gl.GL_FRAMEBUFFER_COMPLETE:
            raise RuntimeError(f"OpenGL framebuffer incomplete (status {status:#x})")
        gl.glDrawBuffers(1, [gl.GL_COLOR_ATTACHMENT0])
        gl.glReadBuffer(gl.GL_COLOR_ATTACHMENT0)
        gl.glViewport(0, 0, self.width, self.height)
        gl.glEnable(gl.GL_DEPTH_TEST)
        gl.glDepthFunc(gl.GL_LESS)
        gl.glDisable(gl.GL_CULL_FACE)
        gl.glDisable(gl.GL_BLEND)
        gl.glEnable(gl.GL_SCISSOR_TEST)
        gl.glClearColor(0.0, 0.0, 0.0, 0.0)
        gl.glClearDepth(1.0)
        gl.glPixelStorei(gl.GL_PACK_ALIGNMENT, 1)
        gl.glUseProgram(self._program)

    def _upload(self, obj_id: int, vertices: np.ndarray, faces: np.ndarray) -> None:
        from OpenGL import GL as gl

        v = np.ascontiguousarray(vertices, dtype=np.float32)
        f = np.ascontiguousarray(faces, dtype=np.uint32).reshape(-1)
        if v.ndim != 2 or v.shape[1] != 3 or len(v) == 0 or f.size == 0 or f.max() >= len(v):
            raise ValueError(f"obj_id {obj_id}: expected vertices [N,3] and faces [F,3] indexing them")
        vao = gl.glGenVertexArrays(1)
        gl.glBindVertexArray(vao)
        vbo, ebo = gl.glGenBuffers(2)
        gl.glBindBuffer(gl.GL_ARRAY_BUFFER, vbo)
        gl.glBufferData(gl.GL_ARRAY_BUFFER, v.nbytes, v, gl.GL_STATIC_DRAW)
        gl.glEnableVertexAttribArray(0)
        gl.glVertexAttribPointer(0, 3, gl.GL_FLOAT, gl.GL_FALSE, 12, ctypes.c_void_p(0))
        gl.glBindBuffer(gl.GL_ELEMENT_ARRAY_BUFFER, ebo)
        gl.glBufferData(gl.GL_ELEMENT_ARRAY_BUFFER, f.nbytes, f, gl.GL_STATIC_DRAW)
        gl.glBindVertexArray(0)
        self._gl_objects[obj_id] = (vao, vbo, ebo, f.size)
        lo, hi = v.min(axis=0).astype(np.float64), v.max(axis=0).astype(np.float64)
        corners = np.stack(np.meshgrid(*zip(lo, hi), indexing="ij"), axis=-1).reshape(-1, 3)
        self._corners[obj_id] = corners

    # ------------------------------------------------------------------ rendering
    def render(self, obj_id: int, TCO: np.ndarray, K: np.ndarray, window: Window) -> np.ndarray:
        """Depth [h,w] float32 (m, 0 = background) of object ``obj_id`` at ``TCO`` [4,4] inside ``window``.

        ``K`` [3,3] is the full image's intrinsics; the result equals ``full[y0:y1, x0:x1]`` of a
        full-image render wherever the object's projection lies inside the window.
        """
        from OpenGL import GL as gl

        if obj_id not in self._gl_objects:
            raise KeyError(f"no mesh for obj_id {obj_id}; known: {sorted(self._gl_objects)}")
        h, w = window.shape
        if h == 0 or w == 0:
            return np.zeros((h, w), np.float32)
        if window.x0 < 0 or window.y0 < 0 or window.x1 > self.width or window.y1 > self.height:
            raise ValueError(f"{window} is not inside the {self.width}x{self.height} image")
        TCO = np.asarray(TCO, dtype=np.float64)
        z = (self._corners[obj_id] @ TCO[:3, :3].T + TCO[:3, 3])[:, 2]
        if z.max() <= NEAR_MIN_M:
            return np.zeros((h, w), np.float32)
        # Clipping planes around the object's bounding box (as the toolkit), with room to spare.
        near = max(NEAR_MIN_M, 0.5 * float(z.min()))
        far = 2.0 * float(z.max()) + 0.01
        self._platform.make_current()
        gl.glBindFramebuffer(gl.GL_FRAMEBUFFER, self._fbo)
        gl.glUseProgram(self._program)
        gl.glUniformMatrix4fv(self._loc_mv, 1, gl.GL_TRUE, TCO.astype(np.float32))
        P = projection_matrix(np.asarray(K, dtype=np.float64), self.width, self.height, near, far)
        gl.glUniformMatrix4fv(self._loc_proj, 1, gl.GL_TRUE, P.astype(np.float32))
        # GL rows count from the bottom: image rows [y0, y1) are window rows [H - y1, H - y0).
        gy = self.height - window.y1
        gl.glScissor(window.x0, gy, w, h)
        gl.glClear(gl.GL_COLOR_BUFFER_BIT | gl.GL_DEPTH_BUFFER_BIT)
        vao, _, _, n = self._gl_objects[obj_id]
        gl.glBindVertexArray(vao)
        gl.glDrawElements(gl.GL_TRIANGLES, n, gl.GL_UNSIGNED_INT, ctypes.c_void_p(0))
        gl.glBindVertexArray(0)
        buf = gl.glReadPixels(window.x0, gy, w, h, gl.GL_RED, gl.GL_FLOAT)
        return np.frombuffer(buf, dtype=np.float32).reshape(h, w)[::-1].copy()

    def close(self) -> None:
        """Release the GL objects and the context (idempotent).

        Only this renderer's context is destroyed; the EGL display is left initialised, because
        ``eglTerminate`` would also invalidate the contexts of other renderers of the process (as
        deleting a pyrender ``OffscreenRenderer`` does: after that, this renderer is unusable too
        and ``close`` only forgets its handles).
        """
        if self._platform is None:
            return
        from OpenGL import EGL
        from OpenGL import GL as gl
        from OpenGL.error import GLError

        platform, self._platform = self._platform, None
        display, context = platform._egl_display, platform._egl_context
        platform._egl_context = None
        platform._egl_display = None  # keeps pyrender's Platform.__del__ from terminating the display
        objects, self._gl_objects = list(self._gl_objects.values()), {}
        if context is None:
            return
        try:
            EGL.eglMakeCurrent(display, EGL.EGL_NO_SURFACE, EGL.EGL_NO_SURFACE, context)
            for vao, vbo, ebo, _ in objects:
                gl.glDeleteVertexArrays(1, [vao])
                gl.glDeleteBuffers(2, [vbo, ebo])
            if self._fbo is not None:
                gl.glDeleteFramebuffers(1, [self._fbo])
                gl.glDeleteRenderbuffers(2, [self._color, self._depth])
            EGL.eglMakeCurrent(display, EGL.EGL_NO_SURFACE, EGL.EGL_NO_SURFACE, EGL.EGL_NO_CONTEXT)
            EGL.eglDestroyContext(display, context)
        except GLError:  # the display was terminated by someone else: nothing left to release
            pass

    def __enter__(self) -> WindowDepthRenderer:
        return self

    def __exit__(self, *exc) -> None:
        self.close()
