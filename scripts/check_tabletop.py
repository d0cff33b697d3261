#!/usr/bin/env python3
"""Independent check of a GLB scene (default scenes/tabletop/tabletop.glb).

* GLB container / glTF structure: chunk layout, 4-byte alignment of every
  bufferView, POSITION min/max, component types.
* Loads the file with trimesh (force='scene'), prints triangle count, bounds
  and surface area.
* Ray-casts (trimesh.ray) a depth image and a base-colour image from every
  camera node at 128x96 (pixel centres, row 0 at the top) and writes them as
  PNGs (upscaled x4 for viewing) into --outdir.

Usage: .venv/bin/python scripts/check_tabletop.py [GLB] [--outdir /tmp]
"""

from __future__ import annotations

import argparse
import json
import math
import struct
from pathlib import Path

import numpy as np
import trimesh
from PIL import Image

REPO = Path(__file__).resolve().parent.parent


def check_structure(path: Path) -> dict:
    data = path.read_bytes()
    magic, version, total = struct.unpack_from("<4sII", data, 0)
    assert magic == b"glTF" and version == 2 and total == len(data), (magic, version, total)
    jlen, jtype = struct.unpack_from("<I4s", data, 12)
    assert jtype == b"JSON" and jlen % 4 == 0
    gltf = json.loads(data[20:20 + jlen])
    off = 20 + jlen
    blen, btype = struct.unpack_from("<I4s", data, off)
    assert btype == b"BIN\x00" and blen % 4 == 0 and off + 8 + blen == len(data)
    assert gltf["buffers"][0]["byteLength"] <= blen
    binchunk = data[off + 8: off + 8 + blen]
    assert "extensionsUsed" not in gltf and "extensions" not in gltf
    for i, bv in enumerate(gltf["bufferViews"]):
        assert bv.get("byteOffset", 0) % 4 == 0, f"bufferView {i} misaligned"
        assert bv.get("byteOffset", 0) + bv["byteLength"] <= blen
    ncomp = {"SCALAR": 1, "VEC2": 2, "VEC3": 3, "VEC4": 4}
    for mesh in gltf["meshes"]:
        for prim in mesh["primitives"]:
            for sem, ai in prim["attributes"].items():
                acc = gltf["accessors"][ai]
                assert acc["componentType"] == 5126, (mesh["name"], sem)
                bv = gltf["bufferViews"][acc["bufferView"]]
                n = ncomp[acc["type"]]
                arr = np.frombuffer(binchunk, "<f4", acc["count"] * n,
                                    bv.get("byteOffset", 0) + acc.get("byteOffset", 0))
                arr = arr.reshape(-1, n)
                if sem == "POSITION":
                    assert acc["min"] == [float(x) for x in arr.min(0)], mesh["name"]
                    assert acc["max"] == [float(x) for x in arr.max(0)], mesh["name"]
                if sem == "NORMAL":
                    assert np.allclose(np.linalg.norm(arr, axis=1), 1, atol=1e-5)
            if "indices" in prim:
                acc = gltf["accessors"][prim["indices"]]
                assert acc["componentType"] == 5125 and acc["count"] % 3 == 0
            else:
                acc = gltf["accessors"][prim["attributes"]["POSITION"]]
                assert acc["count"] % 3 == 0
    for img in gltf.get("images", []):
        bv = gltf["bufferViews"][img["bufferView"]]
        png = binchunk[bv["byteOffset"]: bv["byteOffset"] + bv["byteLength"]]
        assert img["mimeType"] == "image/png" and png[:8] == b"\x89PNG\r\n\x1a\n"
    return gltf


def camera_rays(world: np.ndarray, yfov: float, aspect: float, w: int, h: int):
    t = math.tan(yfov / 2)
    xs = (2 * (np.arange(w) + 0.5) / w - 1) * t * aspect
    ys = (1 - 2 * (np.arange(h) + 0.5) / h) * t
    dx, dy = np.meshgrid(xs, ys)                     # row 0 = top
    d_cam = np.stack([dx, dy, -np.ones_like(dx)], axis=-1).reshape(-1, 3)
    d = d_cam @ world[:3, :3].T
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    o = np.broadcast_to(world[:3, 3], d.shape).copy()
    return o, d


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("glb", nargs="?", type=Path,
                    default=REPO / "scenes" / "tabletop" / "tabletop.glb")
    ap.add_argument("--outdir", type=Path, default=Path("/tmp"))
    ap.add_argument("--width", type=int, default=128)
    ap.add_argument("--height", type=int, default=96)
    args = ap.parse_args()

    gltf = check_structure(args.glb)
    print("structure: ok")

    scene = trimesh.load(args.glb, force="scene")
    # bake the scene graph into one world-space mesh, remembering which
    # geometry (and so which material) each face came from
    meshes, colors = [], []
    for node in scene.graph.nodes_geometry:
        mat, geom = scene.graph[node]
        m = scene.geometry[geom].copy()
        m.apply_transform(mat)
        meshes.append(m)
        c = np.array([0.5, 0.5, 0.5])
        vis = m.visual
        if hasattr(vis, "material"):
            mat_c = getattr(vis.material, "baseColorFactor", None)
            if mat_c is not None:
                c = np.asarray(mat_c[:3], dtype=float)
                if c.max() > 1.0:        # trimesh stores uint8
                    c = c / 255.0
            if getattr(vis.material, "baseColorTexture", None) is not None:
                tex = np.asarray(vis.material.baseColorTexture.convert("RGB")) / 255.0
                c = c * (tex ** 2.2).mean(axis=(0, 1))
        colors.append(np.tile(c, (len(m.faces), 1)))
    world = trimesh.util.concatenate(meshes)
    face_color = np.concatenate(colors)
    print(f"triangles: {len(world.faces)}")
    print(f"bounds: {world.bounds[0].round(4).tolist()} .. {world.bounds[1].round(4).tolist()}")
    print(f"surface area: {world.area:.4f} m^2")
    for name, g in sorted(scene.geometry.items()):
        print(f"  {name:13s} faces {len(g.faces):6d}")

    cams = {c["name"]: c for c in gltf["cameras"]}
    w, h = args.width, args.height
    for node in gltf["nodes"]:
        if "camera" not in node:
            continue
        name = node["name"]
        persp = gltf["cameras"][node["camera"]]["perspective"]
        mat, _ = scene.graph[name]
        o, d = camera_rays(mat, persp["yfov"], persp["aspectRatio"], w, h)
        tri = world.ray.intersects_first(o, d)
        hit = tri >= 0
        depth = np.full(len(d), np.nan)
        albedo = np.zeros((len(d), 3))
        if hit.any():
            loc, ray_idx, tri_idx = world.ray.intersects_location(
                o[hit], d[hit], multiple_hits=False)
            sel = np.flatnonzero(hit)[ray_idx]
            depth[sel] = np.linalg.norm(loc - o[sel], axis=1)
            albedo[sel] = face_color[tri_idx]
        hit = ~np.isnan(depth)
        print(f"{name}: pos {mat[:3, 3].round(4).tolist()} coverage {hit.mean():.3f} "
              f"depth {np.nanmin(depth):.3f}..{np.nanmax(depth):.3f}")
        # edge rows/cols: fraction of border pixels that hit something
        img_hit = hit.reshape(h, w)
        print(f"  border hits: top {img_hit[0].mean():.2f} bottom {img_hit[-1].mean():.2f} "
              f"left {img_hit[:, 0].mean():.2f} right {img_hit[:, -1].mean():.2f}")
        dn = np.zeros(len(d))
        if hit.any():
            lo, hi = np.nanmin(depth), np.nanmax(depth)
            dn[hit] = 1.0 - 0.85 * (depth[hit] - lo) / max(hi - lo, 1e-9)
        up = dict(resample=Image.NEAREST)
        Image.fromarray((dn.reshape(h, w) * 255).astype(np.uint8)).resize(
            (w * 4, h * 4), **up).save(args.outdir / f"depth_{name}.png")
        srgb = np.where(albedo <= 0.0031308, 12.92 * albedo,
                        1.055 * np.clip(albedo, 0, 1) ** (1 / 2.4) - 0.055)
        Image.fromarray((srgb.reshape(h, w, 3) * 255).astype(np.uint8)).resize(
            (w * 4, h * 4), **up).save(args.outdir / f"albedo_{name}.png")
    print(f"images written to {args.outdir}")


if __name__ == "__main__":
    main()
