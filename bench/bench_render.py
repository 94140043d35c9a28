"""Benchmark of the batched renderer: renders/s of B crops per call, RGB+depth and depth-only.

Usage: python bench/bench_render.py [--meshes DIR] [--objects 2 3 4 5 8 9] [--batches 8 32]
       [--resolutions 240x320 120x160] [--calls 10] [--baselines]

Models: ``DIR`` (a BOP ``models/`` folder, default ``data/ycbvsynth/models`` when present), else
the YCB-V library's models written to a temporary folder by ``cosy_lite.synth.objects``. Default
objects: the six textured YCB-V models (16384 faces, 1024x1024 textures). Poses: uniformly random
rotations, the object's centre near the crop's centre, at the depth where its diameter spans the
crop height (a CosyPose crop holds the object's box enlarged ~1.4x). Each configuration: one
warm-up call, then ``--calls`` calls on the same batch, all configurations in turns (so that other
processes' load on a shared machine falls on each alike); the table gives the median and best
renders/s. ``--baselines`` adds, at the first resolution and largest batch: pyrender's own
renderer (on the same GL stack, :mod:`cosy_lite.render.pyrender_scene`) with a Scene per crop and
with one Scene whose nodes are toggled, and this renderer without back-face culling, with one crop in flight, and with the crops
as tiles of one tall framebuffer read back at once (the alternative measured and not kept).
"""

from __future__ import annotations

import argparse
import os
import platform
import tempfile
import time
from functools import partial
from pathlib import Path
from typing import Callable

import numpy as np

TEXTURED_YCBV = [2, 3, 4, 5, 8, 9]
DEFAULT_MODELS = Path("data/ycbvsynth/models")
YCBV_FX = 1066.778  # YCB-V focal length (px) at 640x480; crops use it scaled to their height


def parse_resolution(text: str) -> tuple[int, int]:
    h, w = text.lower().split("x")
    return int(h), int(w)


def crop_batch(meshes: dict, obj_ids: list[int], B: int, resolution: tuple[int, int], seed: int = 0):
    """B random (obj_id, TCO [4,4] m) and the crop K [3,3] at ``resolution`` (H, W)."""
    from scipy.spatial.transform import Rotation

    H, W = resolution
    rng = np.random.default_rng(seed)
    f = YCBV_FX * H / 480
    K = np.array([[f, 0.0, W / 2], [0.0, f, H / 2], [0.0, 0.0, 1.0]])
    ids = [obj_ids[k] for k in rng.integers(0, len(obj_ids), B)]
    TCO = np.tile(np.eye(4), (B, 1, 1))
    TCO[:, :3, :3] = Rotation.random(B, random_state=seed).as_matrix()
    for i, obj_id in enumerate(ids):
        v = np.asarray(meshes[obj_id].vertices)
        diameter = float(np.linalg.norm(v.max(axis=0) - v.min(axis=0)))
        z = f * diameter / H
        TCO[i, :3, 3] = [*(rng.uniform(-0.05, 0.05, 2) * diameter), z]
    return ids, TCO, K


def time_round_robin(fns: list[Callable[[], object]], calls: int) -> list[list[float]]:
    """Seconds of ``calls`` calls of each fn, taken in turns (fn 0, 1, ..., 0, 1, ...) so that the
    load of other processes on a shared machine falls on every fn alike. One warm-up call each."""
    for fn in fns:
        fn()  # meshes uploaded, framebuffers made
    out: list[list[float]] = [[] for _ in fns]
    for _ in range(calls):
        for fn, ts in zip(fns, out):
            t = time.perf_counter()
            fn()
            ts.append(time.perf_counter() - t)
    return out


class PyrenderScenePerCrop:
    """Baseline: pyrender's renderer with a new Scene per crop (each object alone, flat)."""

    def __init__(self, meshes: dict, resolution: tuple[int, int]):
        from cosy_lite.render.pyrender_scene import OffscreenSceneRenderer, pyrender_module

        self.meshes = {i: pyrender_module().Mesh.from_trimesh(m) for i, m in meshes.items()}
        self.renderer = OffscreenSceneRenderer(resolution[1], resolution[0])

    def render(self, ids, TCO, K):
        from cosy_lite.render.gl import CV_TO_GL
        from cosy_lite.render.pyrender_scene import intrinsics_camera, pyrender_module

        pyrender = pyrender_module()
        out = []
        for obj_id, T in zip(ids, TCO):
            scene = pyrender.Scene(bg_color=[0, 0, 0, 0], ambient_light=[1.0, 1.0, 1.0])
            scene.add(self.meshes[obj_id], pose=CV_TO_GL @ T)
            scene.add(intrinsics_camera(K), pose=np.eye(4))
            out.append(self.renderer.render(scene, flags=pyrender.RenderFlags.FLAT))
        return out


class PyrenderSceneToggle:
    """Baseline: one pyrender Scene with every object node added once, toggled visible per crop."""

    def __init__(self, meshes: dict, resolution: tuple[int, int]):
        from cosy_lite.render.pyrender_scene import OffscreenSceneRenderer, intrinsics_camera, pyrender_module

        pyrender = pyrender_module()
        H, W = resolution
        self.scene = pyrender.Scene(bg_color=[0, 0, 0, 0], ambient_light=[1.0, 1.0, 1.0])
        self.nodes = {}
        for obj_id, mesh in meshes.items():
            m = pyrender.Mesh.from_trimesh(mesh)
            for p in m.primitives:
                p.material.baseColorFactor = np.ones(4)  # pyrender takes trimesh's 0.4 diffuse otherwise
            m.is_visible = False
            self.nodes[obj_id] = self.scene.add(m)
        self.camera = intrinsics_camera(np.eye(3))
        self.scene.add(self.camera, pose=np.eye(4))
        self.renderer = OffscreenSceneRenderer(W, H)
        self.flags = pyrender.RenderFlags.FLAT

    def render(self, ids, TCO, K):
        from cosy_lite.render.gl import CV_TO_GL

        self.camera.fx, self.camera.fy, self.camera.cx, self.camera.cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
        out = []
        for obj_id, T in zip(ids, TCO):
            node = self.nodes[obj_id]
            node.mesh.is_visible = True
            self.scene.set_pose(node, CV_TO_GL @ T)
            out.append(self.renderer.render(self.scene, flags=self.flags))
            node.mesh.is_visible = False
        return out


def tiled_pass(gls, fbs, meshes, MVP, z_rows, cull, resolution, rgb, depth, MV=None, shaded=False) -> None:
    """The alternative measured and not kept: crop j drawn as tile j (rows [j H, (j+1) H)) of one
    tall framebuffer, one read-back per channel for all (a drop-in for ``renderer._render_pass``;
    flat colours only: ``MV`` and ``shaded`` are ignored)."""
    from OpenGL import GL as gl

    from cosy_lite.render import renderer as R

    H, W = resolution
    n = len(meshes)
    key = ("tiles", n * H, W)  # kept beside the per-crop framebuffers of the GL state
    if key not in gls.framebuffers:
        gls.framebuffers[key] = [R._create_framebuffer(W, n * H)]
    fb = gls.framebuffers[key][0]
    gl.glBindFramebuffer(gl.GL_FRAMEBUFFER, fb.fbo)
    gl.glDrawBuffers(2, [gl.GL_NONE if rgb is None else gl.GL_COLOR_ATTACHMENT0, gl.GL_COLOR_ATTACHMENT1])
    gl.glViewport(0, 0, W, n * H)
    gl.glScissor(0, 0, W, n * H)
    gl.glClear(gl.GL_COLOR_BUFFER_BIT | gl.GL_DEPTH_BUFFER_BIT)
    for j, mesh in enumerate(meshes):
        if mesh is None:
            continue
        kind = "depth" if rgb is None else ("color" if mesh.texture is None else "texture")
        gl.glUseProgram(gls.programs[kind])
        (gl.glEnable if cull[j] else gl.glDisable)(gl.GL_CULL_FACE)
        gl.glViewport(0, j * H, W, H)
        gl.glScissor(0, j * H, W, H)
        gl.glUniformMatrix4fv(gls.uniforms[kind][0], 1, gl.GL_TRUE, MVP[j])
        gl.glUniform4fv(gls.uniforms[kind][1], 1, z_rows[j])
        if kind == "texture":
            gl.glBindTexture(gl.GL_TEXTURE_2D, mesh.texture)
        gl.glBindVertexArray(mesh.vao)
        gl.glDrawElements(gl.GL_TRIANGLES, mesh.n_indices, gl.GL_UNSIGNED_INT, None)
    gl.glBindVertexArray(0)
    R._read_into(gl.GL_COLOR_ATTACHMENT1, (0, 0, W, n * H), gl.GL_RED, gl.GL_FLOAT, depth)
    if rgb is not None:
        R._read_into(gl.GL_COLOR_ATTACHMENT0, (0, 0, W, n * H), gl.GL_RGB, gl.GL_UNSIGNED_BYTE, rgb)


def render_tiled(renderer, *args, **kwargs):
    """``renderer.render`` with :func:`tiled_pass` in place of the per-crop framebuffers."""
    from cosy_lite.render import renderer as R

    per_crop, R._render_pass = R._render_pass, tiled_pass
    try:
        return renderer.render(*args, **kwargs)
    finally:
        R._render_pass = per_crop


def main(argv: list[str] | None = None) -> None:
    from cosy_lite.geometry.crops import CROP_RESOLUTION

    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--meshes", type=Path, default=None,
                    help="BOP models/ folder (default: data/ycbvsynth/models if present)")
    ap.add_argument("--objects", type=int, nargs="+", default=TEXTURED_YCBV)
    ap.add_argument("--batches", type=int, nargs="+", default=[8, 32])
    half = (CROP_RESOLUTION[0] // 2, CROP_RESOLUTION[1] // 2)
    ap.add_argument("--resolutions", type=parse_resolution, nargs="+", default=[CROP_RESOLUTION, half])
    ap.add_argument("--calls", type=int, default=10)
    ap.add_argument("--baselines", action="store_true")
    args = ap.parse_args(argv)

    from cosy_lite.render.renderer import GlRenderer

    with tempfile.TemporaryDirectory() as tmp:
        models = args.meshes or (DEFAULT_MODELS if DEFAULT_MODELS.is_dir() else None)
        if models is None:
            from cosy_lite.synth.objects import write_bop_models

            write_bop_models(args.objects, Path(tmp))
            models = Path(tmp) / "models"
        renderer = GlRenderer(models_dir=models)
        t = time.perf_counter()
        meshes = {i: renderer.mesh(i) for i in args.objects}
        t_load = time.perf_counter() - t
        t = time.perf_counter()
        renderer.render(args.objects, np.tile(np.eye(4), (len(args.objects), 1, 1)), np.eye(3), (8, 8))
        t_upload = time.perf_counter() - t
        faces = sorted({len(m.faces) for m in meshes.values()})
        print(f"models: {models} objects {args.objects} faces {faces}; {platform.machine()}, {os.cpu_count()} CPUs")
        print(f"first use: read {t_load:.2f} s, upload + cull check {t_upload:.2f} s for {len(meshes)} meshes")
        print("| resolution | batch | output | renders/s (median) | renders/s (best) | ms/call (median) "
              "| mask fraction |")
        print("| --- | --- | --- | --- | --- | --- | --- |")
        cases = []  # (resolution, batch, output, fn, mask fraction)
        for res in args.resolutions:
            for B in args.batches:
                ids, TCO, K = crop_batch(meshes, args.objects, B, res)
                mask = float(renderer.render(ids, TCO, K, res, depth_only=True).mask.mean())
                for depth_only in (False, True):
                    fn = partial(renderer.render, ids, TCO, K, res, depth_only=depth_only)
                    cases.append((res, B, "depth" if depth_only else "rgb+depth", fn, mask))
        if args.baselines:
            res, B = args.resolutions[0], max(args.batches)
            ids, TCO, K = crop_batch(meshes, args.objects, B, res)
            per_scene = PyrenderScenePerCrop(meshes, res)
            toggle = PyrenderSceneToggle(meshes, res)
            no_cull, tiled = GlRenderer(meshes, cull_back_faces=False), GlRenderer(meshes)
            variants = {
                "pyrender, Scene per crop": partial(per_scene.render, ids, TCO, K),
                "pyrender, one Scene, nodes toggled": partial(toggle.render, ids, TCO, K),
                "this, no back-face culling": partial(no_cull.render, ids, TCO, K, res),
                "this, 1 crop in flight": partial(GlRenderer(meshes, max_in_flight=1).render, ids, TCO, K, res),
                "this, crops as tiles of one framebuffer": partial(render_tiled, tiled, ids, TCO, K, res),
            }
            cases += [(res, B, f"rgb+depth, {name}", fn, float("nan")) for name, fn in variants.items()]
        timings = time_round_robin([c[3] for c in cases], args.calls)
        rows = [(f"{r[0]}x{r[1]}", B, out, ts, mask) for (r, B, out, _, mask), ts in zip(cases, timings)]
        for res_s, B, out, ts, mask in rows:
            med, best = float(np.median(ts)), min(ts)
            print(f"| {res_s} | {B} | {out} | {B / med:.0f} | {B / best:.0f} | {1000 * med:.1f} | {mask:.2f} |")


if __name__ == "__main__":
    main()
