"""The one OpenGL stack of the process: EGL contexts and the OpenCV -> OpenGL projection.

Every renderer (render-and-compare, ICP and templates: :class:`~cosy_lite.render.renderer.GlRenderer`;
the evaluator's windowed depth: :mod:`cosy_lite.eval.depth_renderer`; pictures; the synthetic
generator's lit scenes: :mod:`cosy_lite.render.pyrender_scene`) renders in an :class:`EglContext`
of its own, made current only while it renders and destroyed without terminating the EGL display,
so that renderers of any kind can be created and closed in any order in one process.

Pixel convention (as the BOP toolkit's renderer): a point with OpenCV projection
``u = fx x/z + s y/z + cx``, ``v = fy y/z + cy`` lands at window coordinates ``(u, v)``; pixel
``(row r, column c)`` covers ``[c, c+1) x [r, r+1)`` and is sampled at its centre
``(c + 0.5, r + 0.5)``. Masks and depth maps are therefore comparable with those of the toolkit.
"""

from __future__ import annotations

import os

import numpy as np

# OpenCV camera (x right, y down, z forward) -> OpenGL camera (x right, y up, z backward).
CV_TO_GL = np.diag([1.0, -1.0, -1.0, 1.0])


def use_egl() -> None:
    """Select headless EGL for PyOpenGL unless the user chose a platform. Call before importing OpenGL."""
    os.environ.setdefault("PYOPENGL_PLATFORM", "egl")


def projection_matrices(K: np.ndarray, resolution: tuple[int, int], znear: float, zfar: float) -> np.ndarray:
    """Clip-from-camera matrices [B,4,4] for OpenCV cameras K [B,3,3] (skew kept), image (H, W).

    Window x = u and window y = v (not H - v): the framebuffer's first row is the image's top row,
    so read-back needs no flip (and outward counter-clockwise faces appear clockwise). The pixel
    centres are sampled. Camera z in [znear, zfar] (m) maps to NDC [-1, 1].
    """
    H, W = resolution
    P = np.zeros((len(K), 4, 4))
    P[:, 0, 0] = 2.0 * K[:, 0, 0] / W
    P[:, 0, 1] = 2.0 * K[:, 0, 1] / W
    P[:, 0, 2] = 2.0 * K[:, 0, 2] / W - 1.0
    P[:, 1, 1] = 2.0 * K[:, 1, 1] / H
    P[:, 1, 2] = 2.0 * K[:, 1, 2] / H - 1.0
    P[:, 2, 2] = (zfar + znear) / (zfar - znear)
    P[:, 2, 3] = -2.0 * zfar * znear / (zfar - znear)
    P[:, 3, 2] = 1.0
    return P


# ----------------------------------------------------------------------------- EGL contexts

_EGL_PID: int | None = None  # the process that created an EGL context through EglContext


class EglContext:
    """One headless OpenGL 4.1 core context (EGL, no surface), made current only while used.

    Created in the process and thread that renders. Mesa's EGL does not survive ``fork``: a child
    forked after its parent created a context hangs in its first GL call, so creating a context in
    such a child raises instead (use a ``spawn``/``forkserver`` start method, or render only in the
    children). :meth:`destroy` destroys this context only; it never calls ``eglTerminate``, which
    would invalidate every other context of the process (pyrender's ``OffscreenRenderer.delete``
    does terminate the display: this project does not use it).

    Args:
        device_index: EGL device (GPU) index; default: ``$EGL_DEVICE_ID`` (pyrender's variable) or 0.
        load_torchvision: import torchvision first (see below; ~2 s). False only in a process that
            never imports it (the evaluator's): importing torchvision after the first render crashes.
    """

    def __init__(self, device_index: int | None = None, load_torchvision: bool = True):
        global _EGL_PID
        if _EGL_PID is not None and _EGL_PID != os.getpid():
            raise RuntimeError(
                f"process {os.getpid()} was forked from process {_EGL_PID} after that one created an EGL "
                "context; Mesa's EGL hangs in a forked child. Use a 'spawn' or 'forkserver' start method "
                "(e.g. DataLoader(multiprocessing_context='spawn')) or render only in the workers."
            )
        use_egl()
        # torchvision must be loaded before Mesa's EGL: importing it after the first render crashed the
        # process (its LLVM clashed with llvmpipe's; measured here). Without torch (an onnxruntime-only
        # deployment) there is nothing to guard against.
        if load_torchvision:
            try:
                import torchvision  # noqa: F401
            except ImportError:
                pass
        from pyrender.platforms import egl

        if device_index is None:
            device_index = int(os.environ.get("EGL_DEVICE_ID", "0"))
        self._platform = egl.EGLPlatform(1, 1, device=egl.get_device_by_index(device_index))
        self._platform.init_context()  # leaves the context current
        _EGL_PID = os.getpid()
        self.pid = os.getpid()

    def make_current(self) -> None:
        """Make this context current in the calling thread (raises if the display was terminated)."""
        self._platform.make_current()

    def release(self) -> None:
        """Make no context current in this thread (so that another thread may use this one)."""
        from OpenGL import EGL

        EGL.eglMakeCurrent(self._platform._egl_display, EGL.EGL_NO_SURFACE, EGL.EGL_NO_SURFACE, EGL.EGL_NO_CONTEXT)

    def destroy(self) -> None:
        """Destroy the context and every GL object in it (idempotent). In a forked child, only
        forget the parent's handles: any EGL call there would hang."""
        from OpenGL import EGL

        p = self._platform
        if p._egl_context is not None and os.getpid() == self.pid:
            try:
                self.release()
                EGL.eglDestroyContext(p._egl_display, p._egl_context)
            except Exception:  # display already terminated (by someone else): the context is gone
                pass
        # With no handles left, pyrender's Platform.__del__ neither destroys nor eglTerminates.
        p._egl_context = None
        p._egl_display = None

    def __del__(self) -> None:
        try:
            self.destroy()
        except Exception:
            pass
