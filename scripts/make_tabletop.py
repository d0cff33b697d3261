#!/usr/bin/env python3
"""Generate scenes/tabletop/tabletop.glb: a small tabletop scene for lightprobe.

Deterministic (fixed seeds, no timestamps): running it twice gives a
byte-identical GLB.  The GLB is written by hand (json + struct + numpy) per the
glTF 2.0 spec; trimesh is used only for icosphere / box primitives.

Conventions: +Y up, metres, linear albedo in baseColorFactor, baseColor
texture is an sRGB-encoded PNG.

Usage: .venv/bin/python scripts/make_tabletop.py [--out PATH]
"""

from __future__ import annotations

import argparse
import io
import json
import math
import struct
from pathlib import Path

import numpy as np
import trimesh
from PIL import Image

REPO = Path(__file__).resolve().parent.parent
DEFAULT_OUT = REPO / "scenes" / "tabletop" / "tabletop.glb"

# glTF enums
FLOAT = 5126
UINT32 = 5125
ARRAY_BUFFER = 34962
ELEMENT_ARRAY_BUFFER = 34963
LINEAR = 9729
REPEAT = 10497

# camera intrinsics
YFOV = 0.70
ASPECT = 4.0 / 3.0
ZNEAR = 0.01

# table slab
TABLE_X, TABLE_Y, TABLE_Z = 1.6, 0.04, 1.0

MATERIALS = {
    # name: linear RGB albedo (texture multiplies the table's)
    "table": (1.0, 1.0, 1.0),
    "box_red": (0.75, 0.12, 0.10),
    "box_blue": (0.12, 0.22, 0.70),
    "mug": (0.80, 0.62, 0.22),
    "sphere_white": (0.80, 0.80, 0.80),
    "sphere_green": (0.15, 0.60, 0.20),
    "torus": (0.70, 0.35, 0.12),
    "rock": (0.36, 0.32, 0.27),
}


# --------------------------------------------------------------------------
# small math helpers
# --------------------------------------------------------------------------

def normalize(v: np.ndarray) -> np.ndarray:
    v = np.asarray(v, dtype=np.float64)
    n = np.linalg.norm(v, axis=-1, keepdims=True)
    return v / np.where(n == 0.0, 1.0, n)


def quat_y(angle: float) -> list[float]:
    """Quaternion (x, y, z, w) for a rotation of `angle` rad about +Y."""
    return [0.0, math.sin(angle / 2), 0.0, math.cos(angle / 2)]


def rot_y(angle: float) -> np.ndarray:
    c, s = math.cos(angle), math.sin(angle)
    return np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])


def mat_to_quat(m: np.ndarray) -> list[float]:
    """Rotation matrix -> unit quaternion (x, y, z, w), w >= 0."""
    t = np.trace(m)
    if t > 0:
        s = math.sqrt(t + 1.0) * 2
        w, x = 0.25 * s, (m[2, 1] - m[1, 2]) / s
        y, z = (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s
    elif m[0, 0] > m[1, 1] and m[0, 0] > m[2, 2]:
        s = math.sqrt(1.0 + m[0, 0] - m[1, 1] - m[2, 2]) * 2
        w, x = (m[2, 1] - m[1, 2]) / s, 0.25 * s
        y, z = (m[0, 1] + m[1, 0]) / s, (m[0, 2] + m[2, 0]) / s
    elif m[1, 1] > m[2, 2]:
        s = math.sqrt(1.0 + m[1, 1] - m[0, 0] - m[2, 2]) * 2
        w, x = (m[0, 2] - m[2, 0]) / s, (m[0, 1] + m[1, 0]) / s
        y, z = 0.25 * s, (m[1, 2] + m[2, 1]) / s
    else:
        s = math.sqrt(1.0 + m[2, 2] - m[0, 0] - m[1, 1]) * 2
        w, x = (m[1, 0] - m[0, 1]) / s, (m[0, 2] + m[2, 0]) / s
        y, z = (m[1, 2] + m[2, 1]) / s, 0.25 * s
    q = np.array([x, y, z, w])
    q /= np.linalg.norm(q)
    if q[3] < 0:
        q = -q
    return [float(c) for c in q]


def look_at_rotation(eye, target, up=(0.0, 1.0, 0.0)) -> np.ndarray:
    """Camera-to-world rotation: local -Z looks at target, local +Y ~ up."""
    z = normalize(np.subtract(eye, target))  # backward
    x = normalize(np.cross(up, z))
    y = np.cross(z, x)
    return np.stack([x, y, z], axis=1)


def vertex_normals(v: np.ndarray, f: np.ndarray) -> np.ndarray:
    """Area-weighted smooth vertex normals from geometry."""
    fn = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
    n = np.zeros_like(v)
    for k in range(3):
        np.add.at(n, f[:, k], fn)
    return normalize(n)


# --------------------------------------------------------------------------
# meshes: each is a dict(positions, normals?, uvs?, indices?) in local space
# --------------------------------------------------------------------------

def table_mesh() -> dict:
    """Slab 1.6 x 0.04 x 1.0, top face at y = 0; 24 verts with face normals+UVs.

    UV: 1 texture tile per 0.8 m in x and per 0.5 m in z on the top face (the
    top is covered by 2 x 2 tiles); the sides reuse the same scale.
    """
    hx, hz = TABLE_X / 2, TABLE_Z / 2
    y0, y1 = -TABLE_Y, 0.0
    su, sv = 0.8, 0.5
    pos, nrm, uv, idx = [], [], [], []

    def quad(corners, normal, uvs):
        base = len(pos)
        pos.extend(corners)
        nrm.extend([normal] * 4)
        uv.extend(uvs)
        # corners given counter-clockwise seen from outside
        idx.extend([base, base + 1, base + 2, base, base + 2, base + 3])

    def uvq(a, b):  # a, b: 4 in-plane coordinates
        return [(ai / su, bi / sv) for ai, bi in zip(a, b)]

    # top (+y): seen from above, CCW is x->  -z
    c = [(-hx, y1, hz), (hx, y1, hz), (hx, y1, -hz), (-hx, y1, -hz)]
    quad(c, (0, 1, 0), [((x + hx) / su, (z + hz) / sv) for x, _, z in c])
    # bottom (-y)
    c = [(-hx, y0, -hz), (hx, y0, -hz), (hx, y0, hz), (-hx, y0, hz)]
    quad(c, (0, -1, 0), [((x + hx) / su, (z + hz) / sv) for x, _, z in c])
    # front (+z)
    c = [(-hx, y0, hz), (hx, y0, hz), (hx, y1, hz), (-hx, y1, hz)]
    quad(c, (0, 0, 1), uvq([p[0] + hx for p in c], [p[1] for p in c]))
    # back (-z)
    c = [(hx, y0, -hz), (-hx, y0, -hz), (-hx, y1, -hz), (hx, y1, -hz)]
    quad(c, (0, 0, -1), uvq([p[0] + hx for p in c], [p[1] for p in c]))
    # right (+x)
    c = [(hx, y0, hz), (hx, y0, -hz), (hx, y1, -hz), (hx, y1, hz)]
    quad(c, (1, 0, 0), uvq([p[2] + hz for p in c], [p[1] for p in c]))
    # left (-x)
    c = [(-hx, y0, -hz), (-hx, y0, hz), (-hx, y1, hz), (-hx, y1, -hz)]
    quad(c, (-1, 0, 0), uvq([p[2] + hz for p in c], [p[1] for p in c]))

    m = dict(positions=np.array(pos, dtype=np.float64),
             normals=np.array(nrm, dtype=np.float64),
             uvs=np.array(uv, dtype=np.float64), indices=np.array(idx).reshape(-1, 3))
    _check_winding(m, strict=True)
    return m


def box_mesh(extents, *, indexed: bool) -> dict:
    """Axis-aligned box resting on y = 0, centred on x = z = 0. No normals."""
    m = trimesh.creation.box(extents=extents)
    v = np.asarray(m.vertices, dtype=np.float64) + [0.0, extents[1] / 2, 0.0]
    f = np.asarray(m.faces, dtype=np.int64)
    assert m.volume > 0  # outward winding
    if indexed:
        return dict(positions=v, indices=f)
    return dict(positions=v[f.reshape(-1)])  # 36 vertices, drawArrays style


def icosphere_mesh(radius: float, subdivisions: int) -> dict:
    """Icosphere resting on y = 0; normals = normalize(p - centre)."""
    m = trimesh.creation.icosphere(subdivisions=subdivisions, radius=1.0)
    u = normalize(np.asarray(m.vertices, dtype=np.float64))
    centre_y = -u[:, 1].min() * radius
    pos = u * radius + [0.0, centre_y, 0.0]
    return dict(positions=pos, normals=u, indices=np.asarray(m.faces, dtype=np.int64))


def _grid_indices(rows: int, cols: int, wrap_cols: bool, flip: bool = False):
    """Quads of a (rows+1) x cols (wrapped) or (rows+1) x (cols+1) vertex grid."""
    stride = cols if wrap_cols else cols + 1
    out = []
    for i in range(rows):
        for j in range(cols):
            j1 = (j + 1) % cols if wrap_cols else j + 1
            a, b = i * stride + j, i * stride + j1
            c, d = (i + 1) * stride + j1, (i + 1) * stride + j
            tri = [[a, b, c], [a, c, d]]
            if flip:
                tri = [[a, c, b], [a, d, c]]
            out.extend(tri)
    return np.array(out, dtype=np.int64)


def _concat(parts: list[dict]) -> dict:
    pos, nrm, idx, off = [], [], [], 0
    for p in parts:
        pos.append(p["positions"])
        nrm.append(p["normals"])
        idx.append(p["indices"] + off)
        off += len(p["positions"])
    return dict(positions=np.concatenate(pos), normals=np.concatenate(nrm),
                indices=np.concatenate(idx))


def mug_mesh(r_out=0.05, wall=0.006, height=0.11, floor=0.008, seg=64) -> dict:
    """Open-top mug: outer/inner walls, rim, outside bottom, inside floor,
    half-torus handle on +x. Separate vertices at every hard edge."""
    r_in = r_out - wall
    th = np.arange(seg) * (2 * np.pi / seg)
    # ring directions; note (cos, sin) in the x/(-z) plane so that the
    # grid winding below is CCW from outside
    d = np.stack([np.cos(th), np.zeros(seg), -np.sin(th)], axis=1)
    up = np.array([0.0, 1.0, 0.0])

    def wall_part(r, y0, y1, outward: bool):
        pos = np.concatenate([d * r + up * y0, d * r + up * y1])
        nrm = np.concatenate([d, d]) * (1 if outward else -1)
        return dict(positions=pos, normals=nrm,
                    indices=_grid_indices(1, seg, True, flip=not outward))

    def disc_part(r0, r1, y, facing_up: bool):
        """Annulus r0..r1 at height y (r0 = 0 gives a fan around the centre)."""
        if r0 == 0.0:
            pos = np.concatenate([up[None] * y, d * r1 + up * y])
            tris = []
            for j in range(seg):
                a, b = 1 + j, 1 + (j + 1) % seg
                tris.append([0, a, b] if facing_up else [0, b, a])
            idx = np.array(tris, dtype=np.int64)
        else:
            pos = np.concatenate([d * r0 + up * y, d * r1 + up * y])
            idx = _grid_indices(1, seg, True, flip=facing_up)
        n = up if facing_up else -up
        return dict(positions=pos, normals=np.tile(n, (len(pos), 1)), indices=idx)

    parts = [
        wall_part(r_out, 0.0, height, outward=True),
        wall_part(r_in, floor, height, outward=False),
        disc_part(r_in, r_out, height, facing_up=True),   # rim
        disc_part(0.0, r_out, 0.0, facing_up=False),      # outside bottom
        disc_part(0.0, r_in, floor, facing_up=True),      # inside floor
    ]

    # handle: half torus in the x-y plane, ends buried in the wall
    a, b = 0.032, 0.007            # major / minor radius
    cx, cy = r_out - 0.004, height * 0.5
    nu, nv = 24, 16
    u = np.linspace(-np.pi / 2, np.pi / 2, nu + 1)
    v = np.arange(nv) * (2 * np.pi / nv)
    uu, vv = np.meshgrid(u, v, indexing="ij")
    ring = np.stack([np.cos(uu), np.sin(uu), np.zeros_like(uu)], axis=-1)
    nrm = np.cos(vv)[..., None] * ring + np.sin(vv)[..., None] * np.array([0, 0, 1.0])
    pos = np.array([cx, cy, 0.0]) + a * ring + b * nrm
    parts.append(dict(positions=pos.reshape(-1, 3), normals=nrm.reshape(-1, 3),
                      indices=_grid_indices(nu, nv, True, flip=True)))
    m = _concat(parts)
    _check_winding(m)
    return m


def torus_mesh(major=0.08, minor=0.025, nu=96, nv=32) -> dict:
    """Torus lying flat (axis +Y), centred at the origin; analytic normals."""
    u = np.arange(nu) * (2 * np.pi / nu)
    v = np.arange(nv) * (2 * np.pi / nv)
    uu, vv = np.meshgrid(u, v, indexing="ij")
    ring = np.stack([np.cos(uu), np.zeros_like(uu), -np.sin(uu)], axis=-1)
    nrm = np.cos(vv)[..., None] * ring + np.sin(vv)[..., None] * np.array([0, 1.0, 0])
    pos = major * ring + minor * nrm
    # wrap both directions
    idx = []
    for i in range(nu):
        for j in range(nv):
            i1, j1 = (i + 1) % nu, (j + 1) % nv
            a, b, c, d = i * nv + j, i1 * nv + j, i1 * nv + j1, i * nv + j1
            idx.extend([[a, b, c], [a, c, d]])
    m = dict(positions=pos.reshape(-1, 3), normals=nrm.reshape(-1, 3),
             indices=np.array(idx, dtype=np.int64))
    _check_winding(m)
    return m


def rock_mesh(radius=0.12, squash=0.72, seed=1234) -> dict:
    """Icosphere (subdivisions=6) displaced by smooth low-frequency noise."""
    m = trimesh.creation.icosphere(subdivisions=6, radius=1.0)
    u = normalize(np.asarray(m.vertices, dtype=np.float64))
    f = np.asarray(m.faces, dtype=np.int64)
    rng = np.random.default_rng(seed)
    disp = np.zeros(len(u))
    # broad lumps plus a few weaker, shorter bumps (all smooth)
    for lo, hi, amp, count in ((1.2, 3.5, 1.0, 7), (4.0, 8.0, 0.35, 8)):
        for _ in range(count):
            w = normalize(rng.normal(size=3))
            freq = rng.uniform(lo, hi)
            phase = rng.uniform(0, 2 * np.pi)
            disp += amp * np.sin(freq * (u @ w) + phase) / freq
    disp -= disp.mean()
    disp *= 0.25 / np.abs(disp).max()        # +-25 % of the radius
    pos = u * (radius * (1.0 + disp))[:, None]
    pos[:, 1] *= squash
    pos[:, 1] -= pos[:, 1].min()             # rest on the table
    pos[:, 0] -= 0.5 * (pos[:, 0].max() + pos[:, 0].min())
    pos[:, 2] -= 0.5 * (pos[:, 2].max() + pos[:, 2].min())
    out = dict(positions=pos, normals=vertex_normals(pos, f), indices=f)
    _check_winding(out)
    return out


def _check_winding(m: dict, strict: bool = False) -> None:
    """Triangles must be CCW from the side their vertex normals point to."""
    v, f, n = m["positions"], m["indices"], m["normals"]
    fn = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
    agree = np.einsum("ij,ij->i", fn, n[f].sum(axis=1))
    frac = (agree > 0).mean()
    assert frac == 1.0 if strict else frac > 0.999, frac


# --------------------------------------------------------------------------
# texture
# --------------------------------------------------------------------------

def srgb_encode(lin: np.ndarray) -> np.ndarray:
    lin = np.clip(lin, 0.0, 1.0)
    return np.where(lin <= 0.0031308, 12.92 * lin, 1.055 * lin ** (1 / 2.4) - 0.055)


def srgb_decode(s: np.ndarray) -> np.ndarray:
    return np.where(s <= 0.04045, s / 12.92, ((s + 0.055) / 1.055) ** 2.4)


def wood_texture(size=256, seed=7) -> tuple[bytes, float]:
    """Seamlessly tiling plank/wood-grain pattern. Returns (png bytes, mean
    linear albedo over all texels and channels)."""
    rng = np.random.default_rng(seed)
    t = np.arange(size) / size
    u, v = np.meshgrid(t, t, indexing="xy")      # u: column, v: row
    two_pi = 2 * np.pi

    # 4 planks along u (grain runs along v); everything periodic in u and v
    planks = 4
    plank = np.floor(u * planks).astype(int)
    tone = rng.uniform(0.85, 1.15, size=planks)[plank]
    offset = rng.uniform(0, 1, size=planks)[plank]

    # grain: rings across the plank, warped by low-frequency periodic sines
    warp = (0.35 * np.sin(two_pi * (1 * v + offset))
            + 0.15 * np.sin(two_pi * (3 * v + 2 * offset))
            + 0.05 * np.sin(two_pi * (7 * v + u * planks)))
    ring = (u * planks * 3 + warp + offset * 5) % 1.0
    grain = 0.5 + 0.5 * np.cos(two_pi * ring) ** 3
    # fine streaks (periodic noise from integer-frequency sines)
    fine = np.zeros_like(u)
    for _ in range(12):
        fu, fv = rng.integers(8, 40), rng.integers(1, 4)
        fine += np.sin(two_pi * (fu * u + fv * v + rng.uniform()))
    fine /= 12
    lum = tone * (0.80 + 0.22 * grain + 0.10 * fine)
    # dark seam between planks
    du = np.abs(((u * planks) + 0.5) % 1.0 - 0.5) * size / planks  # texels
    lum *= np.where(du < 1.0, 0.45, 1.0)

    base = np.array([0.62, 0.47, 0.31])          # linear wood colour
    lin = np.clip(lum[..., None] * base, 0.02, 0.95)
    srgb8 = np.round(srgb_encode(lin) * 255).astype(np.uint8)
    mean_lin = float(srgb_decode(srgb8 / 255.0).mean())
    buf = io.BytesIO()
    Image.fromarray(srgb8).save(buf, format="PNG", compress_level=9)
    return buf.getvalue(), mean_lin


# --------------------------------------------------------------------------
# GLB writer
# --------------------------------------------------------------------------

class GltfBuilder:
    def __init__(self) -> None:
        self.bin = bytearray()
        self.gltf: dict = {
            "asset": {"version": "2.0", "generator": "lightprobe scripts/make_tabletop.py"},
            "scene": 0,
            "scenes": [],
            "nodes": [],
            "meshes": [],
            "materials": [],
            "cameras": [],
            "textures": [],
            "images": [],
            "samplers": [],
            "accessors": [],
            "bufferViews": [],
            "buffers": [],
        }

    def _view(self, data: bytes, target: int | None) -> int:
        while len(self.bin) % 4:
            self.bin.append(0)
        view = {"buffer": 0, "byteOffset": len(self.bin), "byteLength": len(data)}
        if target is not None:
            view["target"] = target
        self.bin.extend(data)
        self.gltf["bufferViews"].append(view)
        return len(self.gltf["bufferViews"]) - 1

    def accessor(self, arr: np.ndarray, kind: str, *, minmax=False) -> int:
        if kind == "indices":
            a = np.ascontiguousarray(arr, dtype="<u4").reshape(-1)
            acc = {"componentType": UINT32, "type": "SCALAR"}
            target = ELEMENT_ARRAY_BUFFER
        else:
            a = np.ascontiguousarray(arr, dtype="<f4")
            acc = {"componentType": FLOAT, "type": {2: "VEC2", 3: "VEC3"}[a.shape[1]]}
            target = ARRAY_BUFFER
        acc["bufferView"] = self._view(a.tobytes(), target)
        acc["count"] = int(a.shape[0])
        if minmax:
            acc["min"] = [float(x) for x in a.min(axis=0)]
            acc["max"] = [float(x) for x in a.max(axis=0)]
        self.gltf["accessors"].append(acc)
        return len(self.gltf["accessors"]) - 1

    def material(self, name: str, rgb, texture: int | None = None) -> int:
        pbr = {"baseColorFactor": [float(c) for c in rgb] + [1.0],
               "metallicFactor": 0.0, "roughnessFactor": 1.0}
        if texture is not None:
            pbr["baseColorTexture"] = {"index": texture, "texCoord": 0}
        self.gltf["materials"].append({"name": name, "pbrMetallicRoughness": pbr})
        return len(self.gltf["materials"]) - 1

    def texture_png(self, name: str, png: bytes) -> int:
        view = self._view(png, None)
        self.gltf["images"].append({"name": name, "bufferView": view, "mimeType": "image/png"})
        self.gltf["samplers"].append({"magFilter": LINEAR, "minFilter": LINEAR,
                                      "wrapS": REPEAT, "wrapT": REPEAT})
        self.gltf["textures"].append({"name": name, "sampler": len(self.gltf["samplers"]) - 1,
                                      "source": len(self.gltf["images"]) - 1})
        return len(self.gltf["textures"]) - 1

    def mesh(self, name: str, m: dict, material: int) -> int:
        attrs = {"POSITION": self.accessor(m["positions"], "vec", minmax=True)}
        if "normals" in m:
            attrs["NORMAL"] = self.accessor(m["normals"], "vec")
        if "uvs" in m:
            attrs["TEXCOORD_0"] = self.accessor(m["uvs"], "vec")
        prim = {"attributes": attrs, "material": material, "mode": 4}
        if "indices" in m:
            prim["indices"] = self.accessor(m["indices"], "indices")
        self.gltf["meshes"].append({"name": name, "primitives": [prim]})
        return len(self.gltf["meshes"]) - 1

    def node(self, name: str, **kw) -> int:
        n = {"name": name}
        for k, val in kw.items():
            if val is not None:
                n[k] = [float(x) for x in val] if k in ("translation", "rotation", "scale") else val
        self.gltf["nodes"].append(n)
        return len(self.gltf["nodes"]) - 1

    def camera(self, name: str) -> int:
        self.gltf["cameras"].append({"name": name, "type": "perspective", "perspective": {
            "yfov": YFOV, "aspectRatio": ASPECT, "znear": ZNEAR}})
        return len(self.gltf["cameras"]) - 1

    def glb(self, roots: list[int]) -> bytes:
        self.gltf["scenes"] = [{"name": "tabletop", "nodes": roots}]
        while len(self.bin) % 4:
            self.bin.append(0)
        self.gltf["buffers"] = [{"byteLength": len(self.bin)}]
        js = json.dumps(self.gltf, separators=(",", ":")).encode("utf-8")
        js += b" " * (-len(js) % 4)
        total = 12 + 8 + len(js) + 8 + len(self.bin)
        out = bytearray(struct.pack("<4sII", b"glTF", 2, total))
        out += struct.pack("<I4s", len(js), b"JSON") + js
        out += struct.pack("<I4s", len(self.bin), b"BIN\x00") + self.bin
        return bytes(out)


# --------------------------------------------------------------------------
# scene assembly
# --------------------------------------------------------------------------

def trs_matrix(t=(0, 0, 0), yaw=0.0, s=1.0) -> np.ndarray:
    m = np.eye(4)
    m[:3, :3] = rot_y(yaw) * s
    m[:3, 3] = t
    return m


def fit_camera(eye0, target, points: np.ndarray, fill=0.97, recentre_aim=True):
    """Place the eye on the ray target -> eye0 (same viewing direction as the
    nominal pose), re-aim it slightly so that `points` are centred in the
    frame, and choose the distance so that they just fit (max |ndc| == fill
    on the limiting axis). With recentre_aim=False the camera looks exactly
    at `target`. Returns (eye, camera-to-world rotation, aim)."""
    target = np.asarray(target, dtype=np.float64)
    direction = normalize(np.subtract(eye0, target))
    # perspective extremes of a point set are reached on its convex hull
    points = np.asarray(trimesh.convex.convex_hull(points).vertices)
    tan_y = math.tan(YFOV / 2)
    tan_x = tan_y * ASPECT

    def ndc(eye, aim):
        rot = look_at_rotation(eye, aim)
        pc = (points - eye) @ rot        # camera space (x right, y up, -z fwd)
        depth = -pc[:, 2]
        if depth.min() <= ZNEAR:
            return None
        return np.stack([pc[:, 0] / depth / tan_x, pc[:, 1] / depth / tan_y], axis=1)

    def recentre(eye, aim):
        for _ in range(50 if recentre_aim else 0):
            p = ndc(eye, aim)
            if p is None:
                return aim
            centre = 0.5 * (p.min(axis=0) + p.max(axis=0))
            if np.abs(centre).max() < 1e-7:
                break
            rot = look_at_rotation(eye, aim)
            dist = np.linalg.norm(aim - eye)
            aim = aim + (rot[:, 0] * centre[0] * tan_x + rot[:, 1] * centre[1] * tan_y) * dist
        return aim

    def fit_dist(aim):
        lo, hi = 0.3, 10.0
        for _ in range(60):
            mid = 0.5 * (lo + hi)
            eye = target + direction * mid
            p = ndc(eye, recentre(eye, aim))
            if p is None or np.abs(p).max() > fill:
                lo = mid
            else:
                hi = mid
        return hi

    aim = target.copy()
    dist = fit_dist(aim)
    eye = np.round(target + direction * dist, 4)   # tidy numbers in the file
    aim = recentre(eye, aim)
    return eye, look_at_rotation(eye, aim), aim


def build(out: Path, recentre_aim: bool = True) -> dict:
    g = GltfBuilder()
    png, mean_lin = wood_texture()
    tex = g.texture_png("table_wood", png)
    mat = {name: g.material(name, rgb, tex if name == "table" else None)
           for name, rgb in MATERIALS.items()}

    roots: list[int] = []
    world_pts: dict[str, np.ndarray] = {}   # for framing + overlap checks
    tri_count = 0

    def add(name, m, *, t=(0, 0, 0), yaw=0.0, world=None):
        nonlocal tri_count
        mesh = g.mesh(name, m, mat[name])
        rot = quat_y(yaw) if yaw else None
        node = g.node(name, mesh=mesh, translation=t if any(t) else None, rotation=rot)
        w = world if world is not None else trs_matrix(t, yaw)
        p = m["positions"] @ w[:3, :3].T + w[:3, 3]
        world_pts[name] = p
        tri_count += len(m["indices"]) if "indices" in m else len(m["positions"]) // 3
        return node

    roots.append(add("table", table_mesh()))
    roots.append(add("box_red", box_mesh((0.20, 0.15, 0.15), indexed=False),
                     t=(-0.30, 0.0, 0.15), yaw=math.radians(25)))
    roots.append(add("box_blue", box_mesh((0.10, 0.25, 0.10), indexed=True),
                     t=(0.02, 0.0, -0.25), yaw=math.radians(-10)))
    roots.append(add("mug", mug_mesh(), t=(0.10, 0.0, 0.20), yaw=math.radians(-35)))
    roots.append(add("sphere_white", icosphere_mesh(0.10, 4), t=(0.45, 0.0, -0.22)))
    roots.append(add("sphere_green", icosphere_mesh(0.06, 3), t=(-0.60, 0.0, 0.30)))
    roots.append(add("rock", rock_mesh(), t=(-0.45, 0.0, -0.21), yaw=math.radians(40)))

    # torus: child of a transformed parent (translation + yaw + scale 1.25)
    p_t, p_yaw, p_s = (0.48, -0.0125, 0.24), math.radians(30), 1.25
    c_t = (0.03, 0.035, -0.02)   # child y: 1.25 * (0.035 - 0.025) - 0.0125 = 0
    tm = torus_mesh()
    world = trs_matrix(p_t, p_yaw, p_s) @ trs_matrix(c_t)
    torus_mesh_idx = g.mesh("torus", tm, mat["torus"])
    child = g.node("torus", mesh=torus_mesh_idx, translation=c_t)
    roots.append(g.node("torus_parent", children=[child], translation=p_t,
                        rotation=quat_y(p_yaw), scale=(p_s, p_s, p_s)))
    world_pts["torus"] = tm["positions"] @ world[:3, :3].T + world[:3, 3]
    tri_count += len(tm["indices"])

    # sanity: resting on the table, inside the allowed area, no overlaps
    from shapely.geometry import MultiPoint
    hulls = {}
    for name, p in world_pts.items():
        if name == "table":
            continue
        assert abs(p[:, 1].min()) < 1e-6, (name, p[:, 1].min())
        assert p[:, 0].min() >= -0.7 and p[:, 0].max() <= 0.7, name
        assert p[:, 2].min() >= -0.4 and p[:, 2].max() <= 0.4, name
        hulls[name] = MultiPoint(p[:, [0, 2]]).convex_hull
    names = sorted(hulls)
    for i, a in enumerate(names):
        for b in names[i + 1:]:
            assert hulls[a].distance(hulls[b]) > 0.01, (a, b, hulls[a].distance(hulls[b]))

    # cameras: look-at, distance fitted so table + objects fill the frame
    allp = np.concatenate(list(world_pts.values()))
    target = (0.0, 0.06, 0.0)
    cams = {}
    for name, eye0 in (("cam_front", (0.0, 0.95, 1.75)), ("cam_side", (1.75, 0.75, 0.45))):
        eye, r, aim = fit_camera(eye0, target, allp, recentre_aim=recentre_aim)
        cams[name] = (eye, aim)
        roots.append(g.node(name, camera=g.camera(name), translation=eye,
                            rotation=mat_to_quat(r)))

    data = g.glb(roots)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_bytes(data)
    lo = allp.min(axis=0)
    hi = allp.max(axis=0)
    return dict(triangles=tri_count, lo=lo, hi=hi, cams=cams, tex_mean=mean_lin,
                bytes=len(data))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, default=DEFAULT_OUT)
    ap.add_argument("--no-recentre", action="store_true",
                    help="cameras look exactly at (0, 0.06, 0) instead of being "
                         "re-aimed to centre the table and objects in the frame")
    args = ap.parse_args()
    s = build(args.out, recentre_aim=not args.no_recentre)
    fmt = lambda v: "(" + ", ".join(f"{x:.4f}" for x in v) + ")"  # noqa: E731
    cams = " ".join(f"{k}={fmt(e)}->{fmt(a)}" for k, (e, a) in s["cams"].items())
    print(f"wrote {args.out} ({s['bytes']} bytes): {s['triangles']} triangles, "
          f"bounds {fmt(s['lo'])}..{fmt(s['hi'])}, texture mean linear albedo "
          f"{s['tex_mean']:.3f}, {cams}")


if __name__ == "__main__":
    main()
