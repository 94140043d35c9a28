"""Rendering: the batched :class:`Renderer` protocol and its backend (``renderer.py``), pyrender/EGL
plumbing (``gl.py``) and the per-object ``ObjectRenderer`` (``object_renderer.py``)."""

from cosy_lite.render.renderer import PyrenderRenderer, Renderer, RenderOutput

__all__ = ["PyrenderRenderer", "RenderOutput", "Renderer"]
