"""pyrender's own scene renderer (PBR materials, lights, many meshes) on the project's GL stack.

Used for the synthetic generator's lit scenes (:mod:`cosy_lite.synth.scene_render`), which need
pyrender's lighting; single objects on black are :class:`~cosy_lite.render.renderer.GlRenderer`'s.
:class:`OffscreenSceneRenderer` renders exactly what ``pyrender.OffscreenRenderer`` renders (the same
``pyrender.Renderer``), but in an :class:`~cosy_lite.render.gl.EglContext`: closing it destroys
its own context only, where ``OffscreenRenderer.delete`` terminates the EGL display and with it
every other renderer's context in the process.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from cosy_lite.render.gl import CV_TO_GL, EglContext, use_egl


def pyrender_module():
    """Import pyrender with EGL selected (lazy: nothing happens at import of cosy_lite)."""
    use_egl()
    import pyrender

    return pyrender


def camera_node_pose(T_CW: np.ndarray) -> np.ndarray:
    """pyrender camera node pose (camera-to-world, OpenGL axes) from an OpenCV world-to-camera transform."""
    return np.linalg.inv(T_CW) @ CV_TO_GL


def intrinsics_camera(K: np.ndarray, znear: float = 0.01, zfar: float = 20.0):
    """pyrender camera of OpenCV intrinsics ``K`` [3,3] (pixels); same pixel convention as :mod:`.gl`."""
    pyrender = pyrender_module()
    return pyrender.IntrinsicsCamera(
        fx=float(K[0, 0]), fy=float(K[1, 1]), cx=float(K[0, 2]), cy=float(K[1, 2]), znear=znear, zfar=zfar
    )


class OffscreenSceneRenderer:
    """Renders pyrender Scenes offscreen at ``width`` x ``height`` (as ``pyrender.OffscreenRenderer``).

    The context is created here, in the process that renders; it is current only during
    :meth:`render`. Call :meth:`close` when done (idempotent).
    """

    def __init__(self, width: int, height: int, device_index: int | None = None):
        self.width, self.height = int(width), int(height)
        self._context = EglContext(device_index)  # current on creation
        try:
            self._renderer = pyrender_module().Renderer(self.width, self.height)
        finally:
            self._context.release()

    def render(self, scene: Any, flags: int = 0) -> Any:
        """As ``OffscreenRenderer.render``: (rgb [H,W,3] uint8, depth [H,W] float32 m), or depth only
        with ``RenderFlags.DEPTH_ONLY``."""
        pyrender = pyrender_module()
        if self._renderer is None:
            raise RuntimeError("OffscreenSceneRenderer used after close()")
        self._context.make_current()
        try:
            return self._renderer.render(scene, flags | pyrender.RenderFlags.OFFSCREEN)
        finally:
            self._context.release()

    def close(self) -> None:
        """Free the GL objects and this renderer's context (not the display: other renderers live on)."""
        if self._renderer is not None:
            try:
                self._context.make_current()
                self._renderer.delete()
            except Exception:  # the display was terminated by someone else: nothing left to free
                pass
            self._renderer = None
        self._context.destroy()
