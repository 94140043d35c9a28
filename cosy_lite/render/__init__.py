"""Rendering on one OpenGL stack (``gl.py``: EGL contexts, OpenCV -> OpenGL projection): the batched
:class:`Renderer` protocol and its backend ``PyrenderRenderer`` (``renderer.py``: crops, full images,
the evaluator's depth windows) and pyrender's lit scenes for the generator (``pyrender_scene.py``)."""

from cosy_lite.render.renderer import PyrenderRenderer, Renderer, RenderOutput

__all__ = ["PyrenderRenderer", "RenderOutput", "Renderer"]
