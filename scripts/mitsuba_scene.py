#!/usr/bin/env python3
"""Build a Mitsuba 3 scene that matches lightprobe's renderer model.

Used by scripts/check_mitsuba.py (cross-render check) and scripts/bench.py
(speed benchmark). Importable; `python scripts/mitsuba_scene.py` runs
`verify_conventions()` (tiny independent renders, no lightprobe involved) and
prints what it loaded from the bundled scene.

Renderer model reproduced here (see lightprobe's docs):
  * glTF scene, +Y up, metres. World-space meshes come from trimesh
    (scene.graph.nodes_geometry + scene.graph[node] world transforms, so node
    hierarchies such as torus_parent -> torus are respected).
  * Every surface is two-sided Lambertian: `twosided` wrapping `diffuse`.
    Albedo = baseColorFactor x baseColorTexture. The factor is read from the
    glTF JSON, not from trimesh, because trimesh quantises it to uint8
    (0.10 -> 26/255 = 0.102, a 2 % bias). The texture is an sRGB PNG; it is
    decoded to linear here with the exact sRGB curve, multiplied by the factor
    and handed to Mitsuba as `raw` float data with bilinear filtering and
    repeat wrapping (Mitsuba 3 has no mip-mapping either).
  * UVs: glTF's (0, 0) is the image's top-left texel. trimesh flips V on load
    (uv_trimesh = (u, 1 - v)); we undo that and give Mitsuba the glTF UVs
    unchanged, because Mitsuba's bitmap texture also maps v = 0 to the first
    (top) row -- its OBJ loader flips V for that reason. verify_conventions()
    proves it with a render.
  * Shading normals: vertex normals only for primitives whose glTF JSON has a
    NORMAL attribute (trimesh would invent normals for the others); the
    others get no normals, so Mitsuba shades them with flat face normals.
    Normals are transformed by the inverse transpose of the node's matrix.
  * Cameras, lights, albedo overrides and render settings come from
    scripts/scene_truth.py's own reading of the sidecar and glTF, checked against
    `lightprobe info` (never taken from it). Cameras (origin, forward, up, yfov): Mitsuba
    `perspective`, fov_axis 'y', to_world = look_at(origin, origin+forward,
    up); pinhole; `box` reconstruction filter; `independent` sampler
    (sensor_dict/build_scene(sampler=...) picks another, e.g. for
    scripts/bench.py --equal-noise).
  * Sphere lights: `sphere` shapes with an `area` emitter of the given RGB
    radiance and a black BSDF (a light only emits, it reflects nothing),
    hidden from the camera via the path integrator's hide_emitters, plus a
    black occluder sphere just inside each light, because Mitsuba 3.9's
    hidden emitters are transparent to camera rays while lightprobe's occlude.
  * `path` integrator (MIS), max_depth = max_bounces + 1, Russian roulette
    disabled (rr_depth > max_depth). No environment light by default.
  * Optional environment light (build_scene(envmap=...)): Mitsuba's `envmap`
    emitter loading a lat-long EXR written by `lightprobe export-envmap`
    (default target mitsuba) -- or an (H, W, 3) array -- with the default
    to_world (identity: Mitsuba's envmap is +Y up, u = atan2(x, -z)/2pi,
    column j at u = (j+0.5)/W, row i at theta = i*pi/(H-1), which is the
    convention lightprobe exports; scripts/check_mitsuba_envmap.py verifies
    it), never rotated to make a check pass. With hide_emitters, camera rays
    that escape see black, as lightprobe's do. build_scene(sphere_lights=False)
    leaves the sidecar's sphere lights out (render-reference --no-sphere-lights).
"""

from __future__ import annotations

import math
import os
import shutil
import subprocess
import sys
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parent.parent
DEFAULT_SCENE = REPO / "scenes" / "tabletop" / "tabletop.ron"
DEFAULT_BIN = REPO / "target" / "release" / "lightprobe"

# Dr.Jit's LLVM backend needs a working libLLVM: 19 works, 14 is refused and
# 15/16 crash, so point Dr.Jit at 19 explicitly when it is installed.
LLVM_CANDIDATES = (
    "/usr/lib/x86_64-linux-gnu/libLLVM.so.19.1",
    "/usr/lib/x86_64-linux-gnu/libLLVM-19.so",
    "/usr/lib/llvm-19/lib/libLLVM.so.1",
    "/usr/lib/llvm-19/lib/libLLVM.so",
)

# Perturbations for check_mitsuba.py --self-test: each imitates a real bug.
PERTURBATIONS = {
    "mirror": "camera mirrored horizontally (image flipped left-right)",
    "lights_rot30": "light positions rotated 30 deg about +Y",
    "flip_v": "texture V flipped (bottom-left UV origin instead of top-left)",
    "invented_normals": "smooth vertex normals invented for primitives without NORMAL "
                        "(what trimesh's vertex_normals would give the boxes)",
    "albedo_srgb": "texture used without sRGB decoding (gamma bug)",
}


# --------------------------------------------------------------------------
# Mitsuba variant / LLVM
# --------------------------------------------------------------------------

def find_llvm19() -> str | None:
    for p in LLVM_CANDIDATES:
        if os.path.exists(p):
            return p
    return None


def install_llvm19(log=print) -> bool:
    """apt-get install libllvm19 when root; otherwise say how. True if present."""
    if find_llvm19():
        return True
    if os.geteuid() != 0 or not shutil.which("apt-get"):
        log("libllvm19 is missing: run `apt-get update && apt-get install -y libllvm19` "
            "as root (Mitsuba's llvm_ad_rgb needs it)")
        return False
    log("installing libllvm19 with apt-get (Mitsuba's llvm_ad_rgb needs it) ...")
    env = dict(os.environ, DEBIAN_FRONTEND="noninteractive")
    for cmd in (["apt-get", "update", "-qq"], ["apt-get", "install", "-y", "-qq", "libllvm19"]):
        r = subprocess.run(cmd, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
                           text=True)
        if r.returncode != 0:
            log(f"`{' '.join(cmd)}` failed: {r.stderr.strip()[-500:]}")
            return bool(find_llvm19())
    return bool(find_llvm19())


def set_variant(prefer_llvm: bool = True, require_llvm: bool = False, log=print) -> str:
    """Select llvm_ad_rgb (with libLLVM 19) if possible, else scalar_rgb."""
    llvm = find_llvm19()
    if llvm and "DRJIT_LIBLLVM_PATH" not in os.environ:
        os.environ["DRJIT_LIBLLVM_PATH"] = llvm       # must be set before drjit init
    import mitsuba as mi
    if prefer_llvm and llvm:
        try:
            mi.set_variant("llvm_ad_rgb")
            mi.load_dict({"type": "scene"})          # forces the LLVM backend to start
            return mi.variant()
        except Exception as e:  # noqa: BLE001
            if require_llvm:
                raise
            log(f"llvm_ad_rgb unavailable ({e}); falling back to scalar_rgb")
    elif require_llvm:
        raise RuntimeError("llvm_ad_rgb needs libLLVM 19 (apt-get install libllvm19)")
    mi.set_variant("scalar_rgb")
    return mi.variant()


# --------------------------------------------------------------------------
# lightprobe / sidecar / glTF
# --------------------------------------------------------------------------

def described_scene(sidecar: Path, lightprobe_bin: Path = DEFAULT_BIN, log=print) -> dict:
    """The scene as scripts/scene_truth.py reads it (cameras, lights, albedos, settings),
    after checking that `lightprobe info` loaded the same: Mitsuba is built from this
    reading, never from lightprobe's, so a loader bug in lightprobe cannot be copied."""
    import scene_truth
    import time
    for _ in range(20):            # the binary can vanish for a moment while it is rebuilt
        if os.path.exists(lightprobe_bin):
            break
        time.sleep(3)
    return scene_truth.described(Path(sidecar), Path(lightprobe_bin), log=log)


def run_lightprobe(cmd: list[str], retries: int = 20) -> str:
    """Run the lightprobe CLI; the binary can vanish for a moment while it is
    being rebuilt, so wait and retry if it is missing."""
    import time
    for attempt in range(retries):
        if os.path.exists(cmd[0]):
            try:
                r = subprocess.run(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                                   text=True)
            except (FileNotFoundError, PermissionError, OSError):
                r = None
            if r is not None:
                if r.returncode != 0:
                    raise RuntimeError(f"{' '.join(cmd)} failed ({r.returncode}):\n{r.stderr}")
                return r.stdout
        time.sleep(3)
    raise FileNotFoundError(f"{cmd[0]} not found (build it with cargo build --release)")


# The scene's files are read one way for every check (scripts/scene_truth.py).
from scene_truth import read_gltf, sidecar_gltf, srgb_to_linear  # noqa: E402,F401


def read_gltf_json(path: Path) -> dict:
    return read_gltf(path)[0]


@dataclass
class MeshData:
    name: str
    positions: np.ndarray              # (N, 3) world space
    faces: np.ndarray                  # (F, 3) uint32
    normals: np.ndarray | None         # (N, 3) world space, None -> flat shading
    uvs: np.ndarray | None             # (N, 2) glTF convention (0,0 = image top-left)
    albedo: np.ndarray                 # (3,) linear baseColorFactor
    texture_srgb8: np.ndarray | None   # (H, W, 3) uint8 sRGB (row 0 = top)
    extra: dict = field(default_factory=dict)


def load_meshes(glb: Path) -> list[MeshData]:
    """World-space meshes of a glTF via trimesh, with materials/attributes
    cross-checked against the glTF JSON."""
    import trimesh
    from trimesh.util import unique_name

    gltf = read_gltf_json(glb)
    # trimesh names one geometry per primitive with unique_name(mesh name)
    # in glTF order; replicate that to find each geometry's glTF primitive.
    prim_of: dict[str, dict] = {}
    seen: dict = {}
    counts: dict = {}
    for mesh in gltf.get("meshes", []):
        for prim in mesh["primitives"]:
            name = unique_name(mesh.get("name", "GLTF"), seen, counts=counts)
            seen[name] = True
            prim_of[name] = prim
    materials = gltf.get("materials", [])

    scene = trimesh.load(str(glb), force="scene")
    out = []
    for node in scene.graph.nodes_geometry:
        T, gname = scene.graph[node]
        g = scene.geometry[gname]
        prim = prim_of[gname]
        attrs = prim["attributes"]
        assert prim.get("mode", 4) == 4, f"{gname}: only triangle lists are supported"
        T = np.asarray(T, dtype=np.float64)
        v = np.asarray(g.vertices, dtype=np.float64)
        pos = v @ T[:3, :3].T + T[:3, 3]
        faces = np.asarray(g.faces, dtype=np.uint32)
        normals = None
        if "NORMAL" in attrs:
            n = np.asarray(g.vertex_normals, dtype=np.float64)
            nt = np.linalg.inv(T[:3, :3]).T
            n = n @ nt.T
            normals = n / np.linalg.norm(n, axis=1, keepdims=True)
        mat = materials[prim["material"]] if "material" in prim else {}
        pbr = mat.get("pbrMetallicRoughness", {})
        albedo = np.asarray(pbr.get("baseColorFactor", [1, 1, 1, 1])[:3], dtype=np.float64)
        uvs = tex = None
        if "baseColorTexture" in pbr:
            assert pbr["baseColorTexture"].get("texCoord", 0) == 0
            assert "TEXCOORD_0" in attrs, f"{gname}: texture without TEXCOORD_0"
            uv_t = np.asarray(g.visual.uv, dtype=np.float64)
            uvs = np.stack([uv_t[:, 0], 1.0 - uv_t[:, 1]], axis=1)   # undo trimesh's flip
            img = g.visual.material.baseColorTexture
            tex = np.asarray(img.convert("RGB"), dtype=np.uint8)
            # trimesh's factor is uint8-quantised: check it is the same colour
            tf = np.asarray(g.visual.material.baseColorFactor[:3], dtype=np.float64) / 255.0
            assert np.allclose(tf, albedo, atol=1 / 255), (gname, tf, albedo)
        det = float(np.linalg.det(T[:3, :3]))
        if det < 0:
            faces = faces[:, ::-1].copy()     # keep winding vs normals consistent
        out.append(MeshData(node, pos, faces, normals, uvs, albedo, tex,
                            extra=dict(geometry=gname, material=mat.get("name", ""),
                                       det=det)))
    return out


# --------------------------------------------------------------------------
# Mitsuba objects
# --------------------------------------------------------------------------

def _bsdf_dict(md: MeshData, perturb: str | None) -> dict:
    import mitsuba as mi
    if md.texture_srgb8 is None:
        refl = {"type": "rgb", "value": [float(c) for c in md.albedo]}
    else:
        s = md.texture_srgb8.astype(np.float64) / 255.0
        lin = s if perturb == "albedo_srgb" else srgb_to_linear(s)
        lin = (lin * md.albedo[None, None, :]).astype(np.float32)
        if perturb == "flip_v":
            lin = lin[::-1].copy()
        refl = {"type": "bitmap", "bitmap": mi.Bitmap(np.ascontiguousarray(lin)),
                "raw": True, "filter_type": "bilinear", "wrap_mode": "repeat"}
    return {"type": "twosided", "bsdf": {"type": "diffuse", "reflectance": refl}}


def smooth_normals(pos: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Area-weighted vertex normals (as trimesh invents them)."""
    f = faces.astype(np.int64)
    fn = np.cross(pos[f[:, 1]] - pos[f[:, 0]], pos[f[:, 2]] - pos[f[:, 0]])
    n = np.zeros_like(pos)
    for k in range(3):
        np.add.at(n, f[:, k], fn)
    return n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-30)


def mitsuba_mesh(md: MeshData, perturb: str | None = None):
    import mitsuba as mi
    props = mi.Properties()
    props["bsdf"] = mi.load_dict(_bsdf_dict(md, perturb))
    normals = md.normals
    if normals is None and perturb == "invented_normals":
        normals = smooth_normals(md.positions, md.faces)
    has_n = normals is not None
    has_uv = md.uvs is not None
    m = mi.Mesh(md.name, len(md.positions), len(md.faces), props=props,
                has_vertex_normals=has_n, has_vertex_texcoords=has_uv)
    p = mi.traverse(m)
    # the buffers' own types: mi.Float/UInt32 in JIT variants, dr.scalar.ArrayX* in scalar ones
    put = lambda key, a: p.__setitem__(key, type(p[key])(np.ascontiguousarray(a).ravel()))  # noqa: E731
    put("vertex_positions", md.positions.astype(np.float32))
    put("faces", md.faces.astype(np.uint32))
    if has_n:
        put("vertex_normals", normals.astype(np.float32))
    if has_uv:
        put("vertex_texcoords", md.uvs.astype(np.float32))
    p.update()
    return m


def light_dicts(lights: list[dict], perturb: str | None = None) -> dict:
    out = {}
    rot = np.eye(3)
    if perturb == "lights_rot30":
        a = math.radians(30)
        rot = np.array([[math.cos(a), 0, math.sin(a)], [0, 1, 0],
                        [-math.sin(a), 0, math.cos(a)]])
    for i, L in enumerate(lights):
        c = rot @ np.asarray(L["center"], dtype=np.float64)
        if L["radius"] == 0:        # a point light of radiant intensity W/sr
            out[f"light_{i}"] = {"type": "point", "position": [float(x) for x in c],
                                 "intensity": {"type": "rgb",
                                               "value": [float(x) for x in L["intensity"]]}}
            continue
        out[f"light_{i}"] = {
            "type": "sphere", "center": [float(x) for x in c], "radius": float(L["radius"]),
            "emitter": {"type": "area",
                        "radiance": {"type": "rgb", "value": [float(x) for x in L["radiance"]]}},
            "bsdf": {"type": "diffuse", "reflectance": {"type": "rgb", "value": 0.0}},
        }
        # Mitsuba 3.9's hide_emitters lets camera rays pass *through* emitter
        # shapes (measured: a plane behind a hidden sphere light stays
        # visible), while lightprobe's hidden lights occlude the camera
        # (black). A black, non-emitting sphere just inside the light makes
        # Mitsuba occlude too. It cannot shadow the light's own samples: a
        # sampled point on the visible cap is the segment's first contact
        # with the light's ball, and the occluder lies strictly inside it.
        out[f"light_{i}_occluder"] = {
            "type": "sphere", "center": [float(x) for x in c],
            "radius": float(L["radius"]) * 0.999,
            "bsdf": {"type": "diffuse", "reflectance": {"type": "rgb", "value": 0.0}},
        }
    return out


def sensor_dict(cam: dict, spp: int, perturb: str | None = None,
                sampler: str = "independent") -> dict:
    """Mitsuba `perspective` sensor for a lightprobe camera. `sampler` is the
    Mitsuba sampler type; some round spp (ldsampler to a power of 4,
    orthogonal to a prime squared, ...): read sensor.sampler().sample_count()."""
    import mitsuba as mi
    o = np.asarray(cam["origin"], dtype=np.float64)
    f = np.asarray(cam["forward"], dtype=np.float64)
    u = np.asarray(cam["up"], dtype=np.float64)
    to_world = mi.ScalarTransform4f().look_at(origin=o.tolist(), target=(o + f).tolist(),
                                              up=u.tolist())
    if perturb == "mirror":
        to_world = to_world @ mi.ScalarTransform4f().scale([-1.0, 1.0, 1.0])
    return {
        "type": "perspective",
        "fov_axis": "y",
        "fov": math.degrees(cam["yfov"]),
        "near_clip": 1e-3,
        "far_clip": 1e4,
        "to_world": to_world,
        "sampler": {"type": sampler, "sample_count": int(spp)},
        "film": {"type": "hdrfilm", "width": int(cam["width"]), "height": int(cam["height"]),
                 "rfilter": {"type": "box"}, "pixel_format": "rgba",
                 "component_format": "float32", "sample_border": False},
    }


def integrator_dict(max_depth: int) -> dict:
    return {"type": "path", "max_depth": int(max_depth), "rr_depth": int(max_depth) + 100,
            "hide_emitters": True}


def apply_materials(meshes: list[MeshData], desc: dict) -> list[MeshData]:
    """Each mesh's albedo as the scene description has it (glTF material by name, with the
    sidecar's overrides): a Constant override replaces the glTF albedo and texture; an
    image (Map) override is not supported and raises."""
    import dataclasses
    by_name = {m["name"]: m for m in desc.get("materials", [])}
    out = []
    for md in meshes:
        dm = by_name.get(md.extra.get("material", ""))
        if dm is None:
            out.append(md)
        elif "texture" in dm:
            if md.texture_srgb8 is None:
                raise NotImplementedError(f"{md.name}: the sidecar gives a texture (Map "
                                          "override) that the glTF does not have")
            ours = srgb_to_linear(md.texture_srgb8 / 255.0).mean(axis=(0, 1))
            if not np.allclose(ours, dm["texture"]["mean_linear"], atol=1e-3):
                raise NotImplementedError(f"{md.name}: the sidecar replaces the glTF's texture "
                                          "(Map override)")
            out.append(md)
        else:
            a = np.asarray(dm["albedo"], dtype=np.float64)
            if md.texture_srgb8 is not None or not np.allclose(a, md.albedo, atol=1e-6):
                print(f"note: {md.name}: the sidecar's albedo {a.tolist()} overrides the "
                      f"glTF's {md.albedo.tolist()}")
                md = dataclasses.replace(md, albedo=a, texture_srgb8=None, uvs=None)
            out.append(md)
    return out


@dataclass
class MitsubaScene:
    scene: object                      # mi.Scene
    sensors: dict                      # view name -> mi.Sensor
    spp: int
    max_depth: int
    desc: dict                         # the scene as scene_truth.py read it
    meshes: list
    variant: str

    def render(self, view: str, seed: int = 0, spp: int | None = None) -> np.ndarray:
        """(H, W, 4) float32 RGBA, row 0 = top."""
        import mitsuba as mi
        img = mi.render(self.scene, sensor=self.sensors[view], seed=seed,
                        spp=spp or self.spp)
        return np.array(img, dtype=np.float32)


def envmap_dict(envmap) -> dict:
    """Mitsuba `envmap` emitter from a lat-long EXR path or an (H, W, 3)
    float array (Mitsuba convention). Default to_world on purpose: the export
    must be right as it is."""
    import mitsuba as mi
    if isinstance(envmap, (str, Path)):
        return {"type": "envmap", "filename": str(envmap)}
    a = np.ascontiguousarray(np.asarray(envmap, dtype=np.float32)[..., :3])
    return {"type": "envmap", "bitmap": mi.Bitmap(a, mi.Bitmap.PixelFormat.RGB)}


def build_scene(sidecar: Path = DEFAULT_SCENE, lightprobe_bin: Path = DEFAULT_BIN,
                spp: int | None = None, max_depth: int | None = None,
                perturb: str | None = None, desc: dict | None = None,
                meshes: list | None = None, envmap=None,
                sphere_lights: bool = True, sampler: str = "independent") -> MitsubaScene:
    """Mitsuba scene + one sensor per view of a lightprobe sidecar. Call
    set_variant() first. max_depth defaults to the sidecar's max_bounces + 1.
    envmap: lat-long EXR path or (H, W, 3) array for an `envmap` emitter
    (None: no environment light). sphere_lights=False leaves the sidecar's
    sphere lights out. sampler: the sensors' Mitsuba sampler type."""
    import mitsuba as mi
    if perturb is not None and perturb not in PERTURBATIONS:
        raise ValueError(f"unknown perturbation {perturb!r}")
    desc = desc or described_scene(sidecar, lightprobe_bin)
    if desc.get("vertex_colors"):
        raise NotImplementedError(f"{sidecar}: vertex colours (COLOR_0) are not built into "
                                  "the Mitsuba scene")
    settings = desc["settings"]
    spp = int(spp or settings["spp"])
    max_depth = int(max_depth or settings["max_bounces"] + 1)
    meshes = meshes if meshes is not None else load_meshes(sidecar_gltf(sidecar))
    meshes = apply_materials(meshes, desc)
    d = {"type": "scene", "integrator": integrator_dict(max_depth)}
    for i, md in enumerate(meshes):
        d[f"mesh_{i}_{md.name}"] = mitsuba_mesh(md, perturb)
    if sphere_lights:
        d.update(light_dicts(desc["lights"], perturb))
    if envmap is not None:
        d["envmap"] = envmap_dict(envmap)
    scene = mi.load_dict(d)
    sensors = {c["name"]: mi.load_dict(sensor_dict(c, spp, perturb, sampler))
               for c in desc["cameras"]}
    return MitsubaScene(scene, sensors, spp, max_depth, desc, meshes, mi.variant())


# --------------------------------------------------------------------------
# independent convention checks (no lightprobe involved)
# --------------------------------------------------------------------------

def verify_conventions(log=print) -> None:
    """Render a textured quad to prove (1) glTF UVs given to Mitsuba unchanged
    put texel row 0 at the top of the quad, and (2) a camera built with
    sensor_dict() is not mirrored: world +X right of a camera looking down -Z
    with +Y up appears on the image's right, +Y at the top.
    Raises AssertionError on failure."""
    import mitsuba as mi
    # 2x2 texture, row 0 = top: red | green / blue | white
    tex = np.array([[[255, 0, 0], [0, 255, 0]], [[0, 0, 255], [255, 255, 255]]], np.uint8)
    # quad in the plane z = -2, x, y in [-1, 1]; glTF UV (0,0) at top-left (x=-1, y=+1)
    pos = np.array([[-1, 1, -2], [1, 1, -2], [1, -1, -2], [-1, -1, -2]], np.float64)
    uv = np.array([[0, 0], [1, 0], [1, 1], [0, 1]], np.float64) * 0.999 + 0.0005
    md = MeshData("quad", pos, np.array([[0, 1, 2], [0, 2, 3]], np.uint32), None, uv,
                  np.ones(3), tex)
    env = {"type": "constant", "radiance": {"type": "rgb", "value": 1.0}}
    cam = dict(origin=[0, 0, 0], forward=[0, 0, -1], up=[0, 1, 0], yfov=math.radians(40),
               width=64, height=64)
    sensor = mi.load_dict(sensor_dict(cam, 16))

    def quadrants(mesh):
        scene = mi.load_dict({"type": "scene", "integrator": {"type": "path", "max_depth": 2,
                                             "hide_emitters": True},
                              "m": mitsuba_mesh(mesh), "env": env})
        img = np.array(mi.render(scene, sensor=sensor, spp=16))[..., :3]
        q = lambda r, c: img[r * 32 + 8: r * 32 + 24, c * 32 + 8: c * 32 + 24].mean((0, 1))  # noqa: E731
        return {"top-left": q(0, 0), "top-right": q(0, 1), "bottom-left": q(1, 0),
                "bottom-right": q(1, 1)}

    # (1) geometry only: a white square at world x, y in [0.15, 0.85] (camera's
    # right and up) must land in the image's top-right quadrant, nowhere else
    sq = np.array([[0.15, 0.85, -2], [0.85, 0.85, -2], [0.85, 0.15, -2], [0.15, 0.15, -2]])
    got = quadrants(MeshData("square", sq, np.array([[0, 1, 2], [0, 2, 3]], np.uint32), None,
                             None, np.ones(3), None))
    lum = {k: float(v.mean()) for k, v in got.items()}
    assert lum["top-right"] > 0.5 and max(v for k, v in lum.items() if k != "top-right") < 0.05, \
        f"camera mirrored or flipped: quadrant brightness {lum}"
    # (2) texture orientation, with the camera now known to be right
    got = quadrants(md)
    want = {"top-left": 0, "top-right": 1, "bottom-left": 2}   # dominant channel
    for k, ch in want.items():
        assert np.argmax(got[k]) == ch and got[k][ch] > 2 * np.delete(got[k], ch).max(), \
            f"UV convention broken: {k} = {got[k]}"
    assert got["bottom-right"].min() > 0.5, got
    log("conventions OK: glTF UV (0,0) -> texel row 0 appears top-left in the image; "
        "camera not mirrored")


if __name__ == "__main__":
    v = set_variant()
    print("variant:", v)
    verify_conventions()
    sidecar = Path(sys.argv[1]) if len(sys.argv) > 1 else DEFAULT_SCENE
    meshes = load_meshes(sidecar_gltf(sidecar))
    allp = np.concatenate([m.positions for m in meshes])
    print(f"{len(meshes)} meshes, {sum(len(m.faces) for m in meshes)} triangles, bounds "
          f"{allp.min(0).round(4).tolist()} .. {allp.max(0).round(4).tolist()}")
    for m in meshes:
        print(f"  {m.name:14s} tris {len(m.faces):6d} normals {m.normals is not None!s:5s} "
              f"uv {m.uvs is not None!s:5s} albedo {m.albedo.round(4).tolist()}")
