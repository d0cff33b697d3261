#!/usr/bin/env python3
"""Writes a scan-sized test scene: a heightfield patch of ground with a rock on it, as a
photogrammetry or depth-camera scan would give it (one dense mesh, per-vertex colours in
COLOR_0, no textures, no material but the default), and a ring of cameras around it.

    python3 scripts/make_scan.py [--out scenes/scan] [--grid 725] [--views 20]

`--grid 725` gives 2·724² = 1,048,352 triangles on 525,625 vertices (a 27-MB .glb). The sidecar
(`scan.ron`, committed) names the cameras' image size and the lights the references are
rendered under. Standard library only; deterministic.
"""

import argparse
import json
import math
import struct
from array import array
from pathlib import Path

HALF = 1.5  # the patch spans [-HALF, HALF]² metres in x and z


def height(x, z):
    """Ground height in metres: a rock (two overlapping bumps) on gently rolling ground."""
    rock = 0.45 * math.exp(-((x - 0.1) ** 2 + (z + 0.05) ** 2) / 0.12)
    rock += 0.25 * math.exp(-((x + 0.35) ** 2 + (z - 0.25) ** 2) / 0.05)
    ground = 0.04 * math.sin(2.1 * x + 0.5) * math.cos(1.7 * z) + 0.015 * math.sin(9.0 * x + 7.0 * z)
    return rock + ground


def grad(x, z, e=1e-3):
    return (
        (height(x + e, z) - height(x - e, z)) / (2 * e),
        (height(x, z + e) - height(x, z - e)) / (2 * e),
    )


def hash01(i, j):
    """A deterministic value in [0, 1) per grid point (the scan's colour noise)."""
    h = (i * 73856093) ^ (j * 19349663) ^ 0x5BD1E995
    h = (h ^ (h >> 13)) * 0x5BD1E995 & 0xFFFFFFFF
    return ((h ^ (h >> 15)) & 0xFFFF) / 65536.0


def color(x, z, y, i, j):
    """Linear RGB albedo in [0, 1]: soil, the rock greyer with height, speckle noise."""
    soil = (0.42, 0.32, 0.22)
    rock = (0.55, 0.53, 0.50)
    t = min(1.0, max(0.0, (y - 0.06) / 0.2))
    n = 0.85 + 0.3 * hash01(i, j)
    stripe = 0.9 + 0.1 * math.sin(25.0 * (x + 0.3 * z))
    return tuple(min(1.0, ((1 - t) * s + t * r) * n * stripe) for s, r in zip(soil, rock))


def look_at_quaternion(eye, target):
    """glTF rotation (x, y, z, w) turning a camera's −Z toward `target`, +Y up."""
    f = [t - e for t, e in zip(target, eye)]
    fl = math.sqrt(sum(v * v for v in f))
    f = [v / fl for v in f]
    back = [-v for v in f]
    up0 = (0.0, 1.0, 0.0)
    right = [up0[1] * back[2] - up0[2] * back[1], up0[2] * back[0] - up0[0] * back[2], up0[0] * back[1] - up0[1] * back[0]]
    rl = math.sqrt(sum(v * v for v in right))
    right = [v / rl for v in right]
    up = [back[1] * right[2] - back[2] * right[1], back[2] * right[0] - back[0] * right[2], back[0] * right[1] - back[1] * right[0]]
    # Columns right, up, back: the rotation matrix m[row][col].
    m = [[right[0], up[0], back[0]], [right[1], up[1], back[1]], [right[2], up[2], back[2]]]
    tr = m[0][0] + m[1][1] + m[2][2]
    if tr > 0:
        s = 0.5 / math.sqrt(tr + 1.0)
        return [(m[2][1] - m[1][2]) * s, (m[0][2] - m[2][0]) * s, (m[1][0] - m[0][1]) * s, 0.25 / s]
    if m[0][0] > m[1][1] and m[0][0] > m[2][2]:
        s = 2.0 * math.sqrt(1.0 + m[0][0] - m[1][1] - m[2][2])
        return [0.25 * s, (m[0][1] + m[1][0]) / s, (m[0][2] + m[2][0]) / s, (m[2][1] - m[1][2]) / s]
    if m[1][1] > m[2][2]:
        s = 2.0 * math.sqrt(1.0 + m[1][1] - m[0][0] - m[2][2])
        return [(m[0][1] + m[1][0]) / s, 0.25 * s, (m[1][2] + m[2][1]) / s, (m[0][2] - m[2][0]) / s]
    s = 2.0 * math.sqrt(1.0 + m[2][2] - m[0][0] - m[1][1])
    return [(m[0][2] + m[2][0]) / s, (m[1][2] + m[2][1]) / s, 0.25 * s, (m[1][0] - m[0][1]) / s]


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default=str(Path(__file__).resolve().parent.parent / "scenes/scan"))
    ap.add_argument("--grid", type=int, default=725, help="vertices per side (2·(grid−1)² triangles)")
    ap.add_argument("--views", type=int, default=20)
    a = ap.parse_args()
    n = a.grid
    if n < 2 or a.views < 1:
        raise SystemExit("--grid must be at least 2 and --views at least 1")
    pos, nor, col = array("f"), array("f"), array("B")
    lo, hi = [math.inf] * 3, [-math.inf] * 3
    for j in range(n):
        z = -HALF + 2 * HALF * j / (n - 1)
        for i in range(n):
            x = -HALF + 2 * HALF * i / (n - 1)
            y = height(x, z)
            gx, gz = grad(x, z)
            inv = 1.0 / math.sqrt(gx * gx + 1.0 + gz * gz)
            pos.extend((x, y, z))
            nor.extend((-gx * inv, inv, -gz * inv))
            c = color(x, z, y, i, j)
            col.extend((round(c[0] * 255), round(c[1] * 255), round(c[2] * 255), 255))
            for k, v in enumerate((x, y, z)):
                lo[k], hi[k] = min(lo[k], v), max(hi[k], v)
    idx = array("I")
    for j in range(n - 1):
        for i in range(n - 1):
            v = j * n + i
            # Counter-clockwise seen from above (+Y).
            idx.extend((v, v + n, v + 1, v + 1, v + n, v + n + 1))

    blobs = [pos.tobytes(), nor.tobytes(), col.tobytes(), idx.tobytes()]
    offsets, binary = [], b""
    for b in blobs:
        offsets.append(len(binary))
        binary += b + b"\0" * (-len(b) % 4)
    verts = n * n
    cameras, nodes = [], [{"name": "scan", "mesh": 0}]
    for k in range(a.views):
        ang = 2 * math.pi * k / a.views
        r, h = (3.4, 1.5) if k % 2 == 0 else (3.0, 2.3)
        eye = [r * math.sin(ang), h, r * math.cos(ang)]
        nodes.append({
            "name": f"cam{k:02d}",
            "camera": 0,
            "translation": eye,
            "rotation": look_at_quaternion(eye, (0.0, 0.1, 0.0)),
        })
    cameras.append({"type": "perspective", "perspective": {"yfov": 0.75, "znear": 0.01, "aspectRatio": 4 / 3}})
    doc = {
        "asset": {"version": "2.0", "generator": "lightprobe scripts/make_scan.py"},
        "buffers": [{"byteLength": len(binary)}],
        "bufferViews": [
            {"buffer": 0, "byteOffset": offsets[0], "byteLength": len(blobs[0]), "target": 34962},
            {"buffer": 0, "byteOffset": offsets[1], "byteLength": len(blobs[1]), "target": 34962},
            {"buffer": 0, "byteOffset": offsets[2], "byteLength": len(blobs[2]), "target": 34962},
            {"buffer": 0, "byteOffset": offsets[3], "byteLength": len(blobs[3]), "target": 34963},
        ],
        "accessors": [
            {"bufferView": 0, "componentType": 5126, "count": verts, "type": "VEC3", "min": lo, "max": hi},
            {"bufferView": 1, "componentType": 5126, "count": verts, "type": "VEC3"},
            {"bufferView": 2, "componentType": 5121, "normalized": True, "count": verts, "type": "VEC4"},
            {"bufferView": 3, "componentType": 5125, "count": len(idx), "type": "SCALAR"},
        ],
        "meshes": [{"name": "scan", "primitives": [{"attributes": {"POSITION": 0, "NORMAL": 1, "COLOR_0": 2}, "indices": 3}]}],
        "cameras": cameras,
        "nodes": nodes,
        "scenes": [{"nodes": list(range(len(nodes)))}],
        "scene": 0,
    }
    js = json.dumps(doc, separators=(",", ":")).encode()
    js += b" " * (-len(js) % 4)
    glb = struct.pack("<III", 0x46546C67, 2, 12 + 8 + len(js) + 8 + len(binary))
    glb += struct.pack("<II", len(js), 0x4E4F534A) + js
    glb += struct.pack("<II", len(binary), 0x004E4942) + binary
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "scan.glb").write_bytes(glb)
    print(f"{out / 'scan.glb'}: {len(idx) // 3} triangles, {verts} vertices, {a.views} cameras, {len(glb)} bytes")


if __name__ == "__main__":
    main()
