"""Rendering on one OpenGL stack (``gl.py``: EGL contexts, OpenCV -> OpenGL projection): the batched
:class:`Renderer` protocol and its backend ``GlRenderer`` (``renderer.py``: crops, full images,
the evaluator's depth windows) and pyrender's lit scenes for the generator (``pyrender_scene.py``)."""

from cosy_lite.render.renderer import GlRenderer, Renderer, RenderOutput

__all__ = ["GlRenderer", "RenderOutput", "Renderer"]
