"""pyrender plumbing shared by every renderer: EGL set-up, OpenCV <-> OpenGL camera frames.

Pixel convention: pyrender's ``IntrinsicsCamera`` (like the BOP toolkit's renderer) maps a point
with OpenCV projection ``u = fx x/z + cx`` to window coordinate ``u``; pixel ``i`` covers
``[i, i+1)``. Masks and depth maps are therefore comparable with those of the BOP toolkit.
"""

from __future__ import annotations

import os

import numpy as np

# OpenCV camera (x right, y down, z forward) -> OpenGL camera (x right, y up, z backward).
CV_TO_GL = np.diag([1.0, -1.0, -1.0, 1.0])


def use_egl() -> None:
    """Select headless EGL for PyOpenGL unless the user chose a platform. Call before importing pyrender."""
    os.environ.setdefault("PYOPENGL_PLATFORM", "egl")


def pyrender_module():
    """Import pyrender with EGL selected (lazy: nothing happens at import of cosy_lite)."""
    use_egl()
    import pyrender

    return pyrender


def camera_node_pose(T_CW: np.ndarray) -> np.ndarray:
    """pyrender camera node pose (camera-to-world, OpenGL axes) from an OpenCV world-to-camera transform."""
    return np.linalg.inv(T_CW) @ CV_TO_GL


def intrinsics_camera(K: np.ndarray, znear: float = 0.01, zfar: float = 20.0):
    pyrender = pyrender_module()
    return pyrender.IntrinsicsCamera(
        fx=float(K[0, 0]), fy=float(K[1, 1]), cx=float(K[0, 2]), cy=float(K[1, 2]), znear=znear, zfar=zfar
    )


# ----------------------------------------------------------------------------- EGL contexts

_EGL_PID: int | None = None  # the process that created an EGL context through EglContext


class EglContext:
    """One headless OpenGL 4.1 core context (EGL, no surface), made current only while used.

    Created in the process and thread that renders. Mesa's EGL does not survive ``fork``: a child
    forked after its parent created a context hangs in its first GL call, so creating a context in
    such a child raises instead (use a ``spawn``/``forkserver`` start method, or render only in the
    children). :meth:`destroy` destroys this context only; it never calls ``eglTerminate``, which
    would invalidate every other context of the process (pyrender's ``OffscreenRenderer.delete``
    does terminate the display).

    Args:
        device_index: EGL device (GPU) index; default: ``$EGL_DEVICE_ID`` (pyrender's variable) or 0.
    """

    def __init__(self, device_index: int | None = None):
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
            except Exception:  # display already terminated (by another renderer): the context is gone
                pass
        # With no handles left, pyrender's Platform.__del__ neither destroys nor eglTerminates.
        p._egl_context = None
        p._egl_display = None

    def __del__(self) -> None:
        try:
            self.destroy()
        except Exception:
            pass
