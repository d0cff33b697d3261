#!/usr/bin/env python3
"""The scene as the external checks read it themselves, never from lightprobe.

An oracle that took its cameras, lights and albedos from `lightprobe info` would
copy any loader bug of lightprobe's into Mitsuba, Blender and trimesh, and every
check would pass. This module reads the same files with code that shares nothing
with lightprobe's loader:

  * the RON sidecar with a small reader of its own (`parse_ron`): lightprobe uses
    the `ron` crate, so a bug in how lightprobe maps the sidecar to a scene shows
    up as a disagreement;
  * the glTF JSON (and GLB chunks) directly: node transforms composed here
    (matrix or TRS, parent to child), cameras (glTF's look down -Z, +Y up),
    `KHR_lights_punctual` point lights, baseColorFactor and baseColorTexture
    (decoded by Pillow with the exact sRGB curve).

`described(scene, binary)` returns the scene read here, in the shape of
`lightprobe info`'s JSON (cameras, lights, materials, settings), after checking
that lightprobe loaded the same thing; and it proves that comparison can fail:
every mutation from `mutations()` of what lightprobe reported (a wrong albedo,
a moved or brighter light, a turned camera, ...) must be caught, or the check
fails. Tolerances are a few f32 ulp of the values compared; the mutations are
sized far beyond them at any scale. The checks then build their renders from
this reading, not from `info`.

Scope (anything else raises NotImplementedError, naming it): sidecar fields
gltf, views, cameras (LookAt and Matrix poses), image, albedo (Constant and Map
overrides), lights (Sphere, Point), envmap, render; glTF perspective cameras
(orthographic ones are skipped, as lightprobe skips them; mirrored or sheared
ones are refused, as lightprobe refuses them), point lights, baseColorFactor
and 8-bit baseColorTexture (texCoord 0), whether any vertex colour (COLOR_0)
differs from white. `python scripts/scene_truth.py [SCENE] [--height H]`
prints the reading as JSON; `--check LIGHTPROBE SCENE...` compares.
"""

from __future__ import annotations

import base64
import copy
import io
import json
import math
import struct
import subprocess
import sys
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parent.parent

# Defaults of a sidecar that leaves them out, and of a glTF given by itself
# (the sidecar's documented defaults: docs/design.md and schemas/scene.schema.json).
DEFAULT_RENDER = {"spp": 512, "max_bounces": 2, "seed": 1}
DEFAULT_RINGS = 9
DEFAULT_HEIGHT = 480
# KHR_lights_punctual gives intensity in candela; lightprobe renders W/sr.
LUMENS_PER_WATT = 683.0


class TruthError(Exception):
    """The scene could not be read here, or lightprobe loaded something else."""


# ----------------------------------------------------------------------------- RON


class Named:
    """A RON value with a name in front: `Sphere(center: ...)`, `Some(x)`, `Map("a.png")`."""

    def __init__(self, name: str, value):
        self.name, self.value = name, value

    def __repr__(self) -> str:
        return f"Named({self.name!r}, {self.value!r})"


ESCAPES = {"n": "\n", "t": "\t", "r": "\r", "0": "\0", "\\": "\\", '"': '"', "'": "'"}


def _string(text: str, i: int, where: str) -> tuple[str, int]:
    """A RON string starting at text[i] (`"..."` with escapes, or `r#"..."#`): (value, end)."""
    if text[i] == "r":
        j = i + 1
        while text[j] == "#":
            j += 1
        hashes = j - i - 1
        close = '"' + "#" * hashes
        k = text.find(close, j + 1)
        if text[j] != '"' or k < 0:
            raise TruthError(f"{where}: bad raw string at offset {i}")
        return text[j + 1:k], k + len(close)
    j, out = i + 1, []
    while j < len(text) and text[j] != '"':
        if text[j] != "\\":
            out.append(text[j])
            j += 1
            continue
        e = text[j + 1: j + 2]
        if e in ESCAPES:
            out.append(ESCAPES[e])
            j += 2
        elif e == "x":
            out.append(chr(int(text[j + 2:j + 4], 16)))
            j += 4
        elif e == "u" and text[j + 2:j + 3] == "{":
            k = text.index("}", j)
            out.append(chr(int(text[j + 3:k], 16)))
            j = k + 1
        else:
            raise TruthError(f"{where}: unknown escape \\{e} at offset {j}")
    if j >= len(text):
        raise TruthError(f"{where}: unclosed string")
    return "".join(out), j + 1


def _number(word: str):
    try:
        return int(word.replace("_", ""), 0)          # 12, 0x10, 0b101, 1_000
    except ValueError:
        pass
    try:
        return float(word.replace("_", ""))           # 1.5, 1e3, inf, NaN
    except ValueError:
        return None


def _tokens(text: str, where: str):
    i, n = 0, len(text)
    while i < n:
        c = text[i]
        if c.isspace():
            i += 1
        elif text.startswith("//", i):
            j = text.find("\n", i)
            i = n if j < 0 else j
        elif text.startswith("/*", i):               # RON's block comments nest
            depth, i = 1, i + 2
            while depth:
                if i >= n:
                    raise TruthError(f"{where}: unclosed /* comment")
                if text.startswith("/*", i):
                    depth, i = depth + 1, i + 2
                elif text.startswith("*/", i):
                    depth, i = depth - 1, i + 2
                else:
                    i += 1
        elif text.startswith("#![", i):          # extensions: #![enable(implicit_some)]
            j = text.find("]", i)
            i = n if j < 0 else j + 1
        elif c in "()[]{}:,":
            yield c
            i += 1
        elif c == '"' or (c == "r" and text[i + 1:i + 2] in ('"', "#")):
            value, i = _string(text, i, where)
            yield ("str", value)
        else:
            j = i
            while j < n and (text[j].isalnum() or text[j] in "_.+-"):
                if text[j] in "+-" and j > i and text[j - 1] not in "eE":
                    break
                j += 1
            if j == i:
                raise TruthError(f"{where}: unexpected {c!r} at offset {i}")
            word = text[i:j]
            numeric = word[0].isdigit() or word[0] in "+-." or word in ("inf", "NaN")
            num = _number(word) if numeric else None
            if num is not None:
                yield ("num", num)
            elif numeric:
                raise TruthError(f"{where}: bad number {word!r} at offset {i}")
            else:
                yield ("ident", word)
            i = j


def parse_ron(text: str, where: str = "RON"):
    """RON text -> Python: structs and maps become dicts, tuples and lists become lists,
    `Name(...)` a Named (Some(x) becomes x, None None), a bare identifier its name."""
    toks = list(_tokens(text, where))
    pos = 0

    def peek(k=0):
        return toks[pos + k] if pos + k < len(toks) else None

    def take(expected=None):
        nonlocal pos
        t = peek()
        if t is None or (expected is not None and t != expected):
            raise TruthError(f"{where}: expected {expected or 'a value'}, found {t!r}")
        pos += 1
        return t

    def seq(close):             # items up to `close`; named fields make a dict
        fields, items = {}, []
        while peek() != close:
            t = peek()
            if isinstance(t, tuple) and t[0] == "ident" and peek(1) == ":":
                take()
                take(":")
                fields[t[1]] = value()
            else:
                items.append(value())
            if peek() != close:
                take(",")
        take(close)
        if fields and items:
            raise TruthError(f"{where}: a struct mixes named and unnamed fields")
        return fields if fields else items

    def value():
        t = take()
        if t == "(":
            return seq(")")
        if t == "[":
            return seq("]")
        if t == "{":
            out = {}
            while peek() != "}":
                k = value()
                take(":")
                out[k] = value()
                if peek() != "}":
                    take(",")
            take("}")
            return out
        if isinstance(t, tuple):
            kind, v = t
            if kind in ("str", "num"):
                return v
            if v in ("true", "false"):
                return v == "true"
            if v == "None":
                return None
            if peek() == "(":
                take("(")
                inner = seq(")")
                if v == "Some":
                    return inner[0]
                # a newtype variant's one value stands for itself: Map("a.png") -> "a.png"
                return Named(v, inner[0] if isinstance(inner, list) and len(inner) == 1
                             else inner)
            return v
        raise TruthError(f"{where}: unexpected {t!r}")

    out = value()
    if peek() is not None:
        raise TruthError(f"{where}: text after the value: {peek()!r}")
    return out


# ----------------------------------------------------------------------------- glTF


def read_gltf(path: Path) -> tuple[dict, bytes | None]:
    """(JSON, GLB binary chunk or None)."""
    data = Path(path).read_bytes()
    if data[:4] != b"glTF":
        return json.loads(data), None
    jlen, jtype = struct.unpack_from("<I4s", data, 12)
    if jtype != b"JSON":
        raise TruthError(f"{path}: first GLB chunk is not JSON")
    gj = json.loads(data[20:20 + jlen])
    off = 20 + jlen
    binchunk = None
    if off + 8 <= len(data):
        blen, btype = struct.unpack_from("<I4s", data, off)
        if btype == b"BIN\x00":
            binchunk = data[off + 8: off + 8 + blen]
    return gj, binchunk


def _buffer_bytes(gj: dict, binchunk: bytes | None, base: Path, index: int) -> bytes:
    buf = gj["buffers"][index]
    uri = buf.get("uri")
    if uri is None:
        return binchunk or b""
    if uri.startswith("data:"):
        return base64.b64decode(uri.split(",", 1)[1])
    return (base / uri).read_bytes()


def _image_bytes(gj: dict, binchunk, base: Path, image: dict) -> bytes:
    if "bufferView" in image:
        bv = gj["bufferViews"][image["bufferView"]]
        buf = _buffer_bytes(gj, binchunk, base, bv["buffer"])
        start = bv.get("byteOffset", 0)
        return buf[start:start + bv["byteLength"]]
    uri = image["uri"]
    if uri.startswith("data:"):
        return base64.b64decode(uri.split(",", 1)[1])
    return (base / uri).read_bytes()


COMPONENTS = {5120: np.int8, 5121: np.uint8, 5122: np.int16, 5123: np.uint16, 5125: np.uint32,
              5126: np.float32}
WIDTH = {"SCALAR": 1, "VEC2": 2, "VEC3": 3, "VEC4": 4}


def read_accessor(gj: dict, binchunk, base: Path, index: int) -> np.ndarray:
    """An accessor's values as floats (normalized integers scaled to [0, 1] or [-1, 1])."""
    a = gj["accessors"][index]
    if "sparse" in a or "bufferView" not in a:
        raise NotImplementedError("a sparse or buffer-less accessor")
    bv = gj["bufferViews"][a["bufferView"]]
    buf = _buffer_bytes(gj, binchunk, base, bv["buffer"])
    dt = np.dtype(COMPONENTS[a["componentType"]]).newbyteorder("<")
    k = WIDTH[a["type"]]
    stride = bv.get("byteStride") or dt.itemsize * k
    start = bv.get("byteOffset", 0) + a.get("byteOffset", 0)
    if a["count"] and start + (a["count"] - 1) * stride + k * dt.itemsize > len(buf):
        raise TruthError(f"accessor {index} runs past the end of its buffer")
    rows = np.lib.stride_tricks.as_strided(
        np.frombuffer(buf, np.uint8, offset=start), (a["count"], k * dt.itemsize),
        (stride, 1)) if a["count"] else np.zeros((0, k * dt.itemsize), np.uint8)
    x = np.ascontiguousarray(rows).view(dt).reshape(a["count"], k).astype(np.float64)
    if a.get("normalized") and dt.kind in "iu":
        x = x / np.iinfo(dt).max
    return x


def srgb_to_linear(s: np.ndarray) -> np.ndarray:
    return np.where(s <= 0.04045, s / 12.92, ((s + 0.055) / 1.055) ** 2.4)


def texture_summary(png: bytes) -> dict:
    """Width, height and mean linear RGB of an 8-bit sRGB-encoded image."""
    from PIL import Image
    if png[:8] == b"\x89PNG\r\n\x1a\n" and png[24] == 16:
        # Pillow keeps only 8 bits of a 16-bit RGB PNG, and lightprobe reduces it to 8
        # bits its own way: they would agree or differ by rounding, not by loading.
        raise NotImplementedError("a 16-bit PNG texture")
    img = Image.open(io.BytesIO(png)).convert("RGB")
    lin = srgb_to_linear(np.asarray(img, dtype=np.float64) / 255.0)
    return {"width": img.width, "height": img.height,
            "mean_linear": lin.reshape(-1, 3).mean(axis=0).tolist()}


def node_matrix(node: dict) -> np.ndarray:
    """A glTF node's local transform (column-major `matrix`, or T * R * S)."""
    if "matrix" in node:
        return np.asarray(node["matrix"], dtype=np.float64).reshape(4, 4).T
    x, y, z, w = node.get("rotation", [0.0, 0.0, 0.0, 1.0])
    r = np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
        [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
        [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
    ])
    m = np.eye(4)
    m[:3, :3] = r * np.asarray(node.get("scale", [1.0, 1.0, 1.0]))[None, :]
    m[:3, 3] = node.get("translation", [0.0, 0.0, 0.0])
    return m


def world_nodes(gj: dict):
    """(node index, world matrix) of the default scene's nodes, depth first in glTF order."""
    scenes = gj.get("scenes", [])
    if not scenes:
        raise TruthError("the glTF has no scene")
    roots = scenes[gj.get("scene", 0)].get("nodes", [])
    stack = [(i, np.eye(4)) for i in reversed(roots)]
    while stack:
        i, parent = stack.pop()
        node = gj["nodes"][i]
        world = parent @ node_matrix(node)
        yield i, world
        for c in reversed(node.get("children", [])):
            stack.append((c, world))


def camera_from_matrix(name: str, m: np.ndarray, yfov: float, size) -> dict:
    """A camera at a camera-to-world placement: glTF's camera looks down -Z with +Y up."""
    axes = [m[:3, k] / np.linalg.norm(m[:3, k]) for k in range(3)]
    frame = np.stack(axes, axis=1)
    if np.linalg.det(frame) < 0 or np.abs(frame.T @ frame - np.eye(3)).max() > 1e-4:
        # a mirrored or sheared camera has no right/up/forward frame to compare
        raise NotImplementedError(f"camera {name!r}: a mirrored or sheared placement")
    return {"name": name, "origin": m[:3, 3].tolist(), "right": axes[0].tolist(),
            "up": axes[1].tolist(), "forward": (-axes[2]).tolist(), "yfov": float(yfov),
            "width": size[0], "height": size[1]}


def view_size(image: dict | None, height: int | None, aspect: float | None):
    """A view's (width, height): the sidecar's image (scaled to --height), else --height
    (480) at the camera's aspect ratio (4:3 without one)."""
    half_up = lambda x: int(math.floor(x + 0.5))  # noqa: E731 -- not Python's round-half-even
    if image is not None:
        if height is None:
            return int(image["width"]), int(image["height"])
        return max(1, half_up(image["width"] * height / image["height"])), int(height)
    h = int(height or DEFAULT_HEIGHT)
    # glTF's aspectRatio is a float (single precision)
    a = float(np.float32(aspect)) if aspect is not None else 4.0 / 3.0
    return max(1, half_up(h * a)), h


def _struct(v):
    """A struct's fields, whether written `(a: 1)` or with its type's name `Image(a: 1)`."""
    return v.value if isinstance(v, Named) else v


def read_sidecar(scene: Path) -> dict:
    """A RON sidecar's fields."""
    side = _struct(parse_ron(Path(scene).read_text(), str(scene)))
    if not isinstance(side, dict) or "gltf" not in side:
        raise TruthError(f"{scene}: not a sidecar with a gltf field")
    return side


def sidecar_gltf(scene: Path) -> Path:
    """The glTF file a sidecar names, resolved next to it."""
    return Path(scene).resolve().parent / read_sidecar(scene)["gltf"]


def read_scene(scene: Path, height: int | None = None) -> dict:
    """The scene at `scene` (a RON sidecar, or a .gltf/.glb by itself) as this module reads
    it, in the shape of `lightprobe info`: cameras, lights, materials, settings."""
    scene = Path(scene)
    if scene.suffix.lower() in (".gltf", ".glb"):
        side, gltf_path = {}, scene
    else:
        side = read_sidecar(scene)
        known = {"gltf", "views", "cameras", "image", "albedo", "lights", "envmap", "render"}
        if set(side) - known:
            raise NotImplementedError(f"{scene}: fields {sorted(set(side) - known)}")
        gltf_path = scene.parent / side["gltf"]
    gj, binchunk = read_gltf(gltf_path)
    base = gltf_path.parent
    image = _struct(side.get("image"))

    # materials: index 0 is the default material (primitives without one)
    materials = [{"name": "", "albedo": [1.0, 1.0, 1.0]}]
    for k, m in enumerate(gj.get("materials", [])):
        pbr = m.get("pbrMetallicRoughness", {})
        factor = [float(x) for x in pbr.get("baseColorFactor", [1, 1, 1, 1])[:3]]
        name = m.get("name", f"material{k}")
        if "baseColorTexture" in pbr:
            if pbr["baseColorTexture"].get("texCoord", 0) != 0:
                raise NotImplementedError(f"{gltf_path}: material {name!r} uses texCoord != 0")
            tex = gj["textures"][pbr["baseColorTexture"]["index"]]
            png = _image_bytes(gj, binchunk, base, gj["images"][tex["source"]])
            materials.append({"name": name, "albedo_factor": factor,
                              "texture": texture_summary(png)})
        else:
            materials.append({"name": name, "albedo": factor})
    for name, src in (side.get("albedo") or {}).items():
        hits = [m for m in materials if m["name"] == name]
        if not hits:
            raise TruthError(f"{scene}: albedo override of unknown material {name!r}")
        m = hits[0]
        for k in ("albedo", "albedo_factor", "texture"):
            m.pop(k, None)
        if not isinstance(src, Named) or src.name not in ("Constant", "Map"):
            raise NotImplementedError(f"{scene}: albedo override {src!r}")
        if src.name == "Constant":
            m["albedo"] = [float(x) for x in src.value]
        else:
            m["albedo_factor"] = [1.0, 1.0, 1.0]
            m["texture"] = texture_summary((scene.parent / src.value).read_bytes())

    # cameras, glTF lights and vertex colours, walking the node tree
    cameras, gltf_lights, coloured = [], [], False
    overridden = set(side.get("albedo") or {})
    punctual = gj.get("extensions", {}).get("KHR_lights_punctual", {}).get("lights", [])
    for i, world in world_nodes(gj):
        node = gj["nodes"][i]
        for prim in gj["meshes"][node["mesh"]]["primitives"] if "mesh" in node else []:
            mat = prim.get("material")
            name = "" if mat is None else gj["materials"][mat].get("name", f"material{mat}")
            if "COLOR_0" in prim["attributes"] and name not in overridden:
                c = read_accessor(gj, binchunk, base, prim["attributes"]["COLOR_0"])
                coloured |= bool((c[:, :3] != 1.0).any())
        if "camera" in node:
            cam = gj["cameras"][node["camera"]]
            if cam.get("type") == "perspective":
                p = cam["perspective"]
                name = node.get("name") or cam.get("name") or f"camera{i}"
                cameras.append(camera_from_matrix(
                    name, world, p["yfov"], view_size(image, height, p.get("aspectRatio"))))
        ext = node.get("extensions", {}).get("KHR_lights_punctual")
        if ext is not None:
            light = punctual[ext["light"]]
            if light.get("type") != "point":
                raise NotImplementedError(f"{gltf_path}: a {light.get('type')} light")
            colour = np.asarray(light.get("color", [1.0, 1.0, 1.0]), dtype=np.float64)
            intensity = colour * light.get("intensity", 1.0) / LUMENS_PER_WATT
            radius = (light.get("extras") or {}).get("radius",
                                                    (node.get("extras") or {}).get("radius", 0.0))
            centre = world[:3, 3].tolist()
            if radius == 0:
                gltf_lights.append({"center": centre, "radius": 0.0,
                                    "intensity": intensity.tolist()})
            else:
                gltf_lights.append({"center": centre, "radius": float(radius),
                                    "radiance": (intensity / (math.pi * radius ** 2)).tolist()})
    for c in side.get("cameras") or []:
        c = _struct(c)
        pose = c["pose"]
        size = view_size(image, height, c.get("aspect_ratio"))
        if pose.name == "LookAt":
            eye = np.asarray(pose.value["eye"], dtype=np.float64)
            target = np.asarray(pose.value["target"], dtype=np.float64)
            up = np.asarray(pose.value.get("up", [0.0, 1.0, 0.0]), dtype=np.float64)
            back = (eye - target) / np.linalg.norm(eye - target)
            right = np.cross(up, back)
            right /= np.linalg.norm(right)
            m = np.eye(4)
            m[:3, 0], m[:3, 1], m[:3, 2], m[:3, 3] = right, np.cross(back, right), back, eye
        elif pose.name == "Matrix":
            m = np.asarray(pose.value, dtype=np.float64)
        else:
            raise NotImplementedError(f"{scene}: camera pose {pose.name}")
        cameras.append(camera_from_matrix(c["name"], m, c["yfov"], size))
    views = side.get("views") or []
    if views:
        by_name = {c["name"]: c for c in cameras}
        missing = [v for v in views if v not in by_name]
        if missing:
            raise TruthError(f"{scene}: views {missing} are not cameras")
        cameras = [by_name[v] for v in views]

    lights = gltf_lights
    if side.get("lights"):
        lights = []
        for L in side["lights"]:
            v = L.value
            if L.name == "Sphere":
                lights.append({"center": [float(x) for x in v["center"]],
                               "radius": float(v["radius"]),
                               "radiance": [float(x) for x in v["radiance"]]})
            elif L.name == "Point":
                lights.append({"center": [float(x) for x in v["center"]], "radius": 0.0,
                               "intensity": [float(x) for x in v["intensity"]]})
            else:
                raise NotImplementedError(f"{scene}: light {L.name}")

    sizes = {(c["width"], c["height"]) for c in cameras}
    w, h = sizes.pop() if len(sizes) == 1 else (None, None)
    render = {**DEFAULT_RENDER, **_struct(side.get("render") or {})}
    settings = {"width": w, "height": h, "spp": int(render["spp"]),
                "max_bounces": int(render["max_bounces"]), "seed": int(render["seed"]),
                "rings": int(_struct(side.get("envmap") or {}).get("rings", DEFAULT_RINGS))}
    return {"scene": str(scene), "gltf": str(gltf_path), "cameras": cameras, "lights": lights,
            "materials": materials, "vertex_colors": coloured, "settings": settings}


# ----------------------------------------------------------------------------- comparison

# lightprobe holds f32: its values agree with these f64 readings to a few units in the last
# place (ulp) of the values involved. Tolerance: ULPS ulp of the larger magnitude, plus a
# floor for values that are zero up to rounding (a unit vector's component). The mutations
# below are sized far beyond it at any scale.
ULPS = 16
FLOOR = 1e-6
TEXTURE_MEAN = 2e-4     # a texture's mean over many texels: f32 sums in a different order


def tolerance(a, b) -> np.ndarray:
    m = np.maximum(np.abs(np.asarray(a, np.float64)), np.abs(np.asarray(b, np.float64)))
    return ULPS * np.spacing(m.astype(np.float32)).astype(np.float64) + FLOOR * (m < 1.0)


def _close(a, b) -> bool:
    a, b = np.asarray(a, dtype=np.float64), np.asarray(b, dtype=np.float64)
    return a.shape == b.shape and bool(np.all(np.abs(a - b) <= tolerance(a, b)))


def _close_relative(a, b, rel: float = ULPS * 2.0 ** -23) -> bool:
    """For radiometric values, which have no natural absolute scale."""
    a, b = np.asarray(a, dtype=np.float64), np.asarray(b, dtype=np.float64)
    return a.shape == b.shape and bool(np.all(np.abs(a - b) <= rel * np.maximum(
        np.abs(a), np.abs(b))))


def mismatches(truth: dict, info: dict) -> list[str]:
    """What lightprobe loaded (`info`) that differs from this module's reading."""
    out = []
    tn = [c["name"] for c in truth["cameras"]]
    ln = [c["name"] for c in info["cameras"]]
    if tn != ln:
        out.append(f"views {ln}, read here {tn}")
    for t, l in zip(truth["cameras"], info["cameras"]):
        for k in ("origin", "right", "up", "forward", "yfov"):
            if not _close(l[k], t[k]):
                out.append(f"camera {t['name']}: {k} {l[k]}, read here {t[k]}")
        for k in ("width", "height"):
            if l[k] != t[k]:
                out.append(f"camera {t['name']}: {k} {l[k]}, read here {t[k]}")
    if len(truth["lights"]) != len(info["lights"]):
        out.append(f"{len(info['lights'])} lights, read here {len(truth['lights'])}")
    for i, (t, l) in enumerate(zip(truth["lights"], info["lights"])):
        for k, same in (("center", _close), ("radius", _close_relative),
                        ("radiance", _close_relative), ("intensity", _close_relative)):
            if (k in t) != (k in l) or (k in t and not same(l[k], t[k])):
                out.append(f"light {i}: {k} {l.get(k)}, read here {t.get(k)}")
    tm = [m["name"] for m in truth["materials"]]
    lm = [m["name"] for m in info["materials"]]
    if tm != lm:
        out.append(f"materials {lm}, read here {tm}")
    for t, l in zip(truth["materials"], info["materials"]):
        for k in ("albedo", "albedo_factor"):
            if (k in t) != (k in l) or (k in t and not _close(l[k], t[k])):
                out.append(f"material {t['name']!r}: {k} {l.get(k)}, read here {t.get(k)}")
        if ("texture" in t) != ("texture" in l):
            out.append(f"material {t['name']!r}: texture {'texture' in l}, read here "
                       f"{'texture' in t}")
        elif "texture" in t:
            tt, lt = t["texture"], l["texture"]
            if (tt["width"], tt["height"]) != (lt["width"], lt["height"]) or not np.all(
                    np.abs(np.subtract(lt["mean_linear"], tt["mean_linear"])) <= TEXTURE_MEAN):
                out.append(f"material {t['name']!r}: texture {lt}, read here {tt}")
    if truth["vertex_colors"] != info["vertex_colors"]:
        out.append(f"vertex colours {info['vertex_colors']}, read here {truth['vertex_colors']}")
    for k, v in truth["settings"].items():
        if info["settings"].get(k) != v:
            out.append(f"settings.{k} {info['settings'].get(k)}, read here {v}")
    return out


def _turn(v, degrees: float) -> list:
    """v turned about +Y."""
    a = math.radians(degrees)
    x, y, z = v
    return [math.cos(a) * x + math.sin(a) * z, y, -math.sin(a) * x + math.cos(a) * z]


def _moved(p: list, axis: int) -> list:
    """p moved 1 mm along an axis, or 1000 ulp where 1 mm is below f32 precision."""
    q = list(p)
    q[axis] += max(1e-3, 1000 * float(np.spacing(np.float32(abs(q[axis])))))
    return q


def _brighter(rgb: list) -> list:
    """rgb with its largest channel 1% higher (a zero channel could not show it)."""
    q = list(rgb)
    k = int(np.argmax(q))
    q[k] = q[k] * 1.01 if q[k] > 0 else 1e-3
    return q


def mutations(info: dict) -> tuple[list, list[str]]:
    """([(what, info with one deliberate loader bug)], kinds that do not apply to this scene):
    each bug must be caught by `mismatches`."""
    out, absent = [], []

    def mutated(what, edit):
        m = copy.deepcopy(info)
        edit(m)
        out.append((what, m))

    if info["cameras"]:
        def turn(m):
            c = m["cameras"][0]
            for k in ("right", "up", "forward"):
                c[k] = _turn(c[k], 0.1)
        mutated("first camera moved 1 mm", lambda m: m["cameras"][0].__setitem__(
            "origin", _moved(m["cameras"][0]["origin"], 0)))
        mutated("first camera turned 0.1 deg about +Y", turn)
        mutated("first camera's yfov 0.1 deg wider", lambda m: m["cameras"][0].__setitem__(
            "yfov", m["cameras"][0]["yfov"] + math.radians(0.1)))
        mutated("first image one pixel wider", lambda m: m["cameras"][0].__setitem__(
            "width", m["cameras"][0]["width"] + 1))
        if len(info["cameras"]) > 1:
            mutated("views in reverse order", lambda m: m.__setitem__(
                "cameras", m["cameras"][::-1]))
    else:
        absent.append("cameras")
    if info["lights"]:
        L = info["lights"][0]
        key = "radiance" if "radiance" in L else "intensity"
        mutated("first light moved 1 mm", lambda m: m["lights"][0].__setitem__(
            "center", _moved(m["lights"][0]["center"], 1)))
        mutated(f"first light's {key} 1% higher", lambda m: m["lights"][0].__setitem__(
            key, _brighter(m["lights"][0][key])))
        if L.get("radius", 0) > 0:
            mutated("first light's radius 1% larger", lambda m: m["lights"][0].__setitem__(
                "radius", m["lights"][0]["radius"] * 1.01))
        mutated("a light lost", lambda m: m["lights"].pop())
    else:
        absent.append("lights")
    consts = [k for k, m in enumerate(info["materials"]) if "albedo" in m and m["name"]]
    if consts:
        k = consts[0]
        mutated(f"material {info['materials'][k]['name']!r}: albedo 1% off",
                lambda m: m["materials"][k].__setitem__(
                    "albedo", [min(x * 1.01 + 1e-3, 1.0) if x < 0.5 else x * 0.99
                               for x in m["materials"][k]["albedo"]]))
    else:
        absent.append("constant albedos")
    texs = [k for k, m in enumerate(info["materials"]) if "texture" in m]
    if texs:
        k = texs[0]
        mutated(f"material {info['materials'][k]['name']!r}: texture mean 1% off",
                lambda m: m["materials"][k]["texture"].__setitem__(
                    "mean_linear", [x * 1.01 + 1e-3
                                    for x in m["materials"][k]["texture"]["mean_linear"]]))
    else:
        absent.append("textures")
    mutated("vertex colours dropped or invented", lambda m: m.__setitem__(
        "vertex_colors", not m["vertex_colors"]))
    mutated("spp one higher", lambda m: m["settings"].__setitem__(
        "spp", m["settings"]["spp"] + 1))
    mutated("max_bounces one higher", lambda m: m["settings"].__setitem__(
        "max_bounces", m["settings"]["max_bounces"] + 1))
    return out, absent


def lightprobe_info(binary: Path, scene: Path, height: int | None = None) -> dict:
    cmd = [str(binary), "info", str(scene)] + (["--height", str(height)] if height else [])
    r = subprocess.run(cmd, capture_output=True, text=True, stdin=subprocess.DEVNULL)
    if r.returncode != 0:
        raise TruthError(f"{' '.join(cmd)} failed ({r.returncode}):\n{r.stderr}")
    return json.loads(r.stdout)


def _count(items: list, noun: str) -> str:
    return f"{len(items)} {noun}{'' if len(items) == 1 else 's'}"


def described(scene: Path, binary: Path, height: int | None = None, log=print) -> dict:
    """The scene as read here, after checking lightprobe loaded the same (`info`) and that
    the check catches every mutation of what lightprobe reports. Raises TruthError when
    either fails."""
    try:
        truth = read_scene(scene, height)
    except (KeyError, IndexError, TypeError, ValueError) as e:
        raise TruthError(f"{scene}: not readable here ({type(e).__name__}: {e})") from e
    info = lightprobe_info(binary, scene, height)
    bad = mismatches(truth, info)
    if bad:
        raise TruthError(f"lightprobe loaded {scene} differently from this check's own "
                         "reading of the files:\n  " + "\n  ".join(bad))
    bugs, absent = mutations(info)
    missed = [what for what, m in bugs if not mismatches(truth, m)]
    muts = len(bugs)
    if missed:
        raise TruthError("the comparison with lightprobe's `info` missed deliberate bugs: "
                         + "; ".join(missed))
    at = f" at a height of {height} pixels" if height else ""
    log(f"scene {scene}{at}: lightprobe's info agrees with the check's own reading "
        f"({_count(truth['cameras'], 'camera')}, {_count(truth['lights'], 'light')}, "
        f"{_count(truth['materials'], 'material')}, settings); all {muts} deliberate bugs "
        "in the info are caught"
        + (f" (none apply to its {', '.join(absent)}: it has none)" if absent else ""))
    truth["triangles"] = info["triangles"]   # for logs only; check_trimesh compares it
    return truth


def write_feature_sidecar(folder: Path) -> Path:
    """A sidecar using what the committed scenes do not: posed cameras (LookAt with its
    aspect ratio, Matrix), Constant and Map albedo overrides, point and sphere lights,
    struct names, comments and extensions. Next to a copy of the bundled glTF."""
    from PIL import Image
    import shutil
    folder.mkdir(parents=True, exist_ok=True)
    shutil.copy(REPO / "scenes" / "tabletop" / "tabletop.glb", folder / "tabletop.glb")
    rng = np.random.default_rng(1)
    Image.fromarray((rng.random((16, 24, 3)) * 255).astype("uint8")).save(folder / "map.png")
    p = folder / "features.ron"
    p.write_text("""#![enable(implicit_some)]
/* every feature the committed scenes leave out */
Scene(
    gltf: "tabletop.glb",
    views: ["posed", "cam_side", "placed"],
    cameras: [
        (name: "posed", yfov: 0.6, aspect_ratio: 1.5,
         pose: LookAt(eye: (1.0, 2.0, 3.0), target: (0, 0.1, 0), up: (0.1, 1, 0))),
        CameraDesc(name: "placed", yfov: 0.9, pose: Matrix((
            (0.0, 0.0, 1.0, 1.0), (0.0, 1.0, 0.0, 0.5), (-1.0, 0.0, 0.0, 2.0), (0, 0, 0, 1)))),
    ],
    albedo: { "mug": Constant((0.8, 0.15, 0.1)), "table": Map("map.png"),
              "box_red": Constant([0.5, 0.25, 0.125]) },
    lights: [
        Point(center: (1, 2, 3), intensity: (10, 20, 30)),
        Sphere(center: (0, 5, 0), radius: 0.1, radiance: (1e3, 2e3, 3e3)),
    ],
    envmap: EnvmapDesc(rings: 5),
    render: (spp: 16, seed: 7), // max_bounces left at its default
)
""")
    return p


WRONG_LOADER = """#!{python}
# lightprobe with a loader bug: its `info` reports the first constant albedo 5% too bright.
import json, subprocess, sys
r = subprocess.run([{binary!r}] + sys.argv[1:], capture_output=True, text=True)
if r.returncode or sys.argv[1:2] != ["info"]:
    sys.stdout.write(r.stdout); sys.stderr.write(r.stderr); sys.exit(r.returncode)
info = json.loads(r.stdout)
m = next(m for m in info["materials"] if "albedo" in m and m["name"])
m["albedo"] = [x * 1.05 for x in m["albedo"]]
print(json.dumps(info))
"""


def wrong_loader_is_caught(scene: Path, binary: Path, folder: Path) -> None:
    """End to end: a lightprobe whose `info` carries a loader bug must fail the check."""
    fake = folder / "lightprobe-with-a-bug"
    fake.write_text(WRONG_LOADER.format(python=sys.executable, binary=str(Path(binary).resolve())))
    fake.chmod(0o755)
    try:
        described(scene, fake, log=lambda s: None)
    except TruthError as e:
        print(f"a lightprobe whose info has an albedo 5% off fails the check, as it must: "
              f"{str(e).splitlines()[1].strip()}", file=sys.stderr)
        return
    raise TruthError("a lightprobe reporting a wrong albedo passed the check")


def main() -> None:
    import argparse
    import tempfile
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("scenes", type=Path, nargs="*",
                    default=[REPO / "scenes" / "tabletop" / "tabletop.ron"])
    ap.add_argument("--height", type=int)
    ap.add_argument("--check", type=Path, metavar="LIGHTPROBE",
                    help="compare each scene with this lightprobe binary's `info` (and run "
                         "the mutation test) instead of printing the reading as JSON")
    ap.add_argument("--features", action="store_true",
                    help="with --check: also a generated sidecar using every feature read here")
    a = ap.parse_args()
    try:
        if not a.check:
            print(json.dumps(read_scene(a.scenes[0], a.height), indent=1))
            return
        with tempfile.TemporaryDirectory() as tmp:
            scenes = list(a.scenes)
            if a.features:
                scenes.append(write_feature_sidecar(Path(tmp)))
            for scene in scenes:
                for height in ([a.height] if a.height else [None, 48]):
                    described(scene, a.check, height)
            wrong_loader_is_caught(scenes[0], a.check, Path(tmp))
    except (TruthError, NotImplementedError, OSError) as e:
        sys.exit(f"error: {e}")


if __name__ == "__main__":
    main()
