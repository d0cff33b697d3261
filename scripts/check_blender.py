#!/usr/bin/env python3
"""Cross-render check: lightprobe's `export-envmap --target blender` in Blender/Cycles.

Blender is a real client here: bpy 5.0.1 (Blender as a Python module, in its
own venv .venv-blender, made by scripts/setup-blender-venv.sh, because it needs
numpy < 2) imports the bundled glTF with its own importer, loads the exported
lat-long EXR as the World's Environment Texture and renders with Cycles on the
CPU. This script runs in the main .venv (numpy 2, Mitsuba's Bitmap as an
independent EXR reader/writer, check_mitsuba.judge); it starts itself under
.venv-blender/bin/python with `--blender-worker JOB.json` for everything bpy.

What it does (default: the bundled tabletop, its 2 views, 128x96, 512 spp):
 A. Grid and export, no rendering:
    1. writes a non-trivial 9-ring envmap.ron with scripts/ring_grid.py (the
       one of check_mitsuba_envmap.py: dim sky, bluer upward, per-cell
       variation, darker ground, a warm bright cell high up at front-left and
       a blue bright cell low at right-back);
    2. `lightprobe export-envmap --target blender --width W` must equal this
       script's own rasterisation of the grid in Blender's convention, written
       from the measured mapping (docs/design.md), bit for bit:
       u = (j+0.5)/W = 0.5 + atan2(g.z, g.x)/2pi, theta = (i+0.5)pi/H from +Y;
    3. `lightprobe import-envmap --target blender` of it gives the cells back.
 B. Blender, no lightprobe rendering involved:
    1. scene set-up facts: every imported camera equals the one built from
       scripts/scene_truth.py's reading of the scene, itself checked against
       `lightprobe info` (glTF -> Blender axes (x, y, z) -> (x, -z, y)); the
       importer's corner normals equal the glTF NORMALs (flat face normals
       where a primitive has none); materials are exactly the scene's albedos
       (texture: same mean linear albedo);
    2. lookup test: Cycles renders the bare World (meshes hidden, film opaque)
       through 6 cube-face cameras (64x64, 90 deg, 16 spp); every pixel whose
       footprint lies inside one ring cell must show that cell's radiance
       (to 1e-4). Cells have distinct values (+-15 % per-cell variation), so
       this pins the axes, azimuth origin and handedness over the whole
       sphere. On a mismatch it reports which rotation / mirror of the
       direction would have matched.
 C. Renders: lightprobe `render-reference --envmap envmap.ron
    --no-sphere-lights` with the sidecar's seed and --seed2; Cycles with
    Blender seeds 0 and 1 (settings below). Compared per view with
    check_mitsuba.judge() (per-channel bias, pixel relMAE ratio vs the ratio
    expected from noise alone, 8x8 block relMAE ratio and 2 % cap) and its
    thresholds (justified there; re-measured for Cycles below), cross-checked
    with `lightprobe compare`; background pixels must be 0 in both.
 D. Self-test (unless --no-self-test): Cycles renders at --self-test-spp of
    deliberately wrong exports -- the blender export rotated 90 deg in azimuth
    (columns rolled by W/4), mirrored in azimuth, and lightprobe's *mitsuba*
    target export loaded as if it were the blender one (a quarter turn the
    other way: Mitsuba's u = atan2(x, -z)/2pi is Blender's u - 1/4) -- must
    FAIL the judge in every view (and the lookup test), while the correct
    export at the same spp (the control) must PASS. It also pins the bounce
    count (unless --no-bounce-test): Cycles max_bounces 0 must PASS against
    lightprobe --max-bounces 1, and Cycles max_bounces + 1 must FAIL against
    lightprobe's max_bounces.

Thresholds: check_mitsuba.py's judge() and thresholds (bias 1 %, pixel
ratio/expected 1.15, block ratio/expected 1.5, block relMAE 2 % at >= 256
spp), unchanged; plus coverage: mean |alpha Blender - alpha lp| over the
ratio expected from both renderers' seed-to-seed alpha noise < 1.5.
Measured with Cycles (bpy 5.0.1, tabletop, W = 4096; results are
deterministic, run to run):
  512 spp: pixel ratio/expected 0.98-1.01 (raw ratio 0.75-0.77: Cycles' Sobol
           + MIS render is ~3x less noisy than lightprobe's, relMAE floor
           0.0126 vs 0.038), block ratio/expected 0.99-1.05, coverage
           ratio/expected 0.98-1.01, bias -0.14..-0.27 %;
  128 spp (control): pixel 1.01-1.03, block 0.99-1.05, bias -0.09..-0.23 %;
  wrong exports (128 spp): pixel ratio/expected 3.8-6.0, block 21-36, bias
           up to 18 %; Cycles max_bounces 2 vs lightprobe 2: bias +0.7..+1.6 %
           (red), block ratio/expected 2.4-2.7.
The small negative bias (Cycles darker by ~0.15-0.25 %, < 1/4 of the budget)
was taken apart (direct light only, 6 lightprobe seeds, W up to 16384, a
constant-albedo table): lightprobe seeds 1 and 2 happen to sit +0.1 % above
the 6-seed mean in cam_front; Cycles' bilinear World lookup at W = 4096
shrinks the bright cells by ~half a pixel (-0.08 % at 4096, -0.35 % at 1024,
scaling as 1/W); Cycles interpolates the 8-bit sRGB texture before decoding it
(computed: -0.07 % on the table's mean albedo; lightprobe and Mitsuba decode
first); what remains is ~-0.05..-0.1 % against lightprobe, the size of the
lightprobe-vs-Mitsuba difference recorded in check_mitsuba_envmap.py. With a
constant envmap (no cell edges) the whole bias is -0.05..-0.08 %.

Cycles settings, each chosen to match lightprobe's model (docs/design.md):
  * Materials: every material is replaced by a Diffuse BSDF with Roughness 0
    (Cycles' Lambert, f = albedo/pi; roughness > 0 is Oren-Nayar), colour =
    glTF baseColorFactor x baseColorTexture. Not the importer's Principled
    BSDF: even at roughness 1 and metallic 0 it has a dielectric specular
    layer (IOR 1.5, F0 = 4 %) on top of the diffuse one and scales the diffuse
    by the layer's albedo, so it is not a Lambertian of the base colour.
    Cycles shades both sides of a surface (the normal is flipped towards the
    incoming ray), like lightprobe's two-sided diffuse.
  * The table's texture: the importer's image (a packed sRGB PNG, colour space
    sRGB), UV map from the importer (it flips V for Blender's bottom-up image
    rows), Linear interpolation, Repeat extension; Cycles on the CPU has no
    mip-mapping, like lightprobe (bilinear, repeat).
  * Normals: the importer's (custom normals from NORMAL, flat faces where a
    primitive has none; verified in B.1). Shadow-terminator offsets set to 0
    on every object (Cycles' default geometry offset 0.1 moves shadow-ray
    origins of smooth meshes, which lightprobe does not do).
  * Cameras from scripts/scene_truth.py (origin, forward, up, yfov), converted to
    Blender axes; sensor fit Vertical, angle = yfov, 128x96, pixel aspect 1.
  * Light paths: lightprobe's max_bounces = 2 counts scattering events
    (camera -> s1 -> s2 -> light: direct light at s1 and at s2). Cycles'
    Max Bounces counts the bounces after the first hit: 0 = direct light only
    (camera -> s1 -> light), 1 = one indirect bounce. So Cycles max_bounces =
    diffuse_bounces = max_bounces - 1 = 1 (glossy, transmission, volume 0;
    no caustics; clamping off: sample_clamp_indirect defaults to 10, which
    would clip bright indirect samples; filter glossy 0; light threshold 0;
    path guiding off). The self-test measures it: Cycles max_bounces 0
    matches lightprobe --max-bounces 1, and Cycles 2 is brighter than
    lightprobe 2 (the extra third scattering event: +0.7..+1.6 % in red).
  * Film: box pixel filter of width 1 pixel (uniform jitter in the pixel, as
    lightprobe); transparent film, so camera rays that escape add 0 (lightprobe
    renders the directly seen envmap black) and alpha = coverage; no
    denoising, no adaptive sampling, fixed seed (use_animated_seed off),
    Tabulated Sobol pattern; view transform Standard, look None, exposure 0
    (the EXR is scene-linear anyway); output EXR float32 RGBA, compositing off.
  * World: Environment Texture (equirectangular, Linear interpolation) of the
    exported EXR, colour space Linear Rec.709 (Blender's scene-linear), default
    mapping (no rotation: the export must be right as it is); importance map
    (sampling method Manual) at the image width (a measured pitfall).

Cost: ~105 s on 2 cores (Blender worker ~85 s: 4 renders at 512 spp ~7.5 s
each, 16 at 128 spp, the lookup renders; lightprobe ~15 s), install excluded
(setup-blender-venv.sh: a 374 MB wheel, ~965 MB venv).

Usage:
  bash scripts/setup-blender-venv.sh         # once: .venv-blender (bpy 5.0.1)
  .venv/bin/python scripts/check_blender.py [--spp N] [--width W]
      [--workdir DIR] [--no-self-test] [--self-test-spp N] [--no-bounce-test]
"""

from __future__ import annotations

import argparse
import json
import math
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
REPO = HERE.parent
DEFAULT_BLENDER_PY = REPO / ".venv-blender" / "bin" / "python"
CUBE_RES = 64          # lookup test: 6 cube faces of CUBE_RES^2 pixels
CUBE_SPP = 16
ALPHA_RATIO_MAX = 1.5  # coverage mismatch / noise (measured 0.98-1.01; see the docstring)


def log(msg: str = "") -> None:
    print(msg, flush=True)


def g2b(v) -> list:
    """glTF (x, y, z) -> Blender (x, -z, y): what Blender's glTF importer does."""
    return [float(v[0]), float(-v[2]), float(v[1])]


def cube_faces() -> list[tuple[str, list, list]]:
    """(name, forward, up) in glTF axes of the 6 lookup-test cameras."""
    return [("px", [1, 0, 0], [0, 1, 0]), ("nx", [-1, 0, 0], [0, 1, 0]),
            ("pz", [0, 0, 1], [0, 1, 0]), ("nz", [0, 0, -1], [0, 1, 0]),
            ("py", [0, 1, 0], [0, 0, 1]), ("ny", [0, -1, 0], [0, 0, -1])]


# ==========================================================================
# Blender side (runs under .venv-blender/bin/python; imports bpy)
# ==========================================================================

def _glb_json_and_bin(path: Path):
    import struct
    data = Path(path).read_bytes()
    assert data[:4] == b"glTF", "expects a .glb"
    jlen, _ = struct.unpack_from("<I4s", data, 12)
    gj = json.loads(data[20:20 + jlen])
    off = 20 + jlen
    blen, _ = struct.unpack_from("<I4s", data, off)
    return gj, data[off + 8: off + 8 + blen]


def _accessor(gj, binchunk, idx) -> np.ndarray:
    a = gj["accessors"][idx]
    bv = gj["bufferViews"][a["bufferView"]]
    assert a["componentType"] == 5126 and a["type"] == "VEC3", a
    start = bv.get("byteOffset", 0) + a.get("byteOffset", 0)
    stride = bv.get("byteStride", 12)
    raw = np.frombuffer(binchunk, dtype=np.uint8, count=stride * (a["count"] - 1) + 12,
                        offset=start)
    return np.lib.stride_tricks.as_strided(raw, shape=(a["count"], 12), strides=(stride, 1)) \
        .copy().view(np.float32).reshape(a["count"], 3).astype(np.float64)


def worker_main(job_file: str) -> int:
    import bpy
    from mathutils import Matrix, Vector

    job = json.loads(Path(job_file).read_text())
    rep: dict = {"blender": bpy.app.version_string}
    t0 = time.time()
    bpy.ops.wm.read_factory_settings(use_empty=True)
    bpy.ops.import_scene.gltf(filepath=job["gltf"])     # importer defaults
    rep["import_seconds"] = time.time() - t0
    scene = bpy.context.scene
    desc = job["desc"]          # the scene as scripts/scene_truth.py read it
    gj, binchunk = _glb_json_and_bin(Path(job["gltf"]))

    # ---- B.1 cameras: the scene's own reading -> Blender, checked against the importer's
    def cam_matrix(c) -> Matrix:
        r, u, f, o = (Vector(g2b(c[k])) for k in ("right", "up", "forward", "origin"))
        m = Matrix.Identity(4)
        for i in range(3):
            m[i][0], m[i][1], m[i][2], m[i][3] = r[i], u[i], -f[i], o[i]
        return m

    cams, cam_check = {}, {}
    for c in desc["cameras"]:
        data = bpy.data.cameras.new("lp_" + c["name"])
        data.type = "PERSP"
        data.sensor_fit = "VERTICAL"
        data.angle_y = c["yfov"]
        data.shift_x = data.shift_y = 0.0
        data.clip_start, data.clip_end = 1e-3, 1e4
        ob = bpy.data.objects.new("lp_" + c["name"], data)
        scene.collection.objects.link(ob)
        ob.matrix_world = cam_matrix(c)
        cams[c["name"]] = ob
        imp = bpy.data.objects.get(c["name"])
        if imp is not None and imp.type == "CAMERA":
            d = max(abs(imp.matrix_world[i][j] - ob.matrix_world[i][j])
                    for i in range(4) for j in range(4))
            cam_check[c["name"]] = {"imported_matrix_max_diff": d,
                                    "imported_yfov": imp.data.angle_y,
                                    "imported_sensor_fit": imp.data.sensor_fit,
                                    "yfov": c["yfov"]}
        else:
            cam_check[c["name"]] = {"imported": None}
    rep["cameras"] = cam_check

    # ---- B.1 normals: Blender's corner normals vs the glTF's
    gl_mats = gj.get("materials", [])
    mesh_of_node = {n["name"]: n["mesh"] for n in gj["nodes"] if "mesh" in n}
    normals_rep = {}
    for ob in [o for o in scene.objects if o.type == "MESH"]:
        me = ob.data
        gmesh = gj["meshes"][mesh_of_node[ob.name]]
        pos_l, nrm_l = [], []
        for prim in gmesh["primitives"]:
            p = _accessor(gj, binchunk, prim["attributes"]["POSITION"])
            pos_l.append(p)
            n = (_accessor(gj, binchunk, prim["attributes"]["NORMAL"])
                 if "NORMAL" in prim["attributes"] else None)
            nrm_l.append(n)
        has_n = all(n is not None for n in nrm_l)
        nl = len(me.loops)
        cn = np.empty(nl * 3)
        me.corner_normals.foreach_get("vector", cn)
        cn = cn.reshape(-1, 3)
        lv = np.empty(nl, dtype=np.int64)
        me.loops.foreach_get("vertex_index", lv)
        co = np.empty(len(me.vertices) * 3)
        me.vertices.foreach_get("co", co)
        co = co.reshape(-1, 3)
        if has_n:
            gp = np.concatenate(pos_l)
            gn = np.concatenate(nrm_l)
            gp_b = np.stack([gp[:, 0], -gp[:, 2], gp[:, 1]], 1)
            gn_b = np.stack([gn[:, 0], -gn[:, 2], gn[:, 1]], 1)
            gn_b /= np.linalg.norm(gn_b, axis=1, keepdims=True)
            # candidates per position (quantised to 1e-5 m)
            key = lambda a: [tuple(k) for k in np.round(a / 1e-5).astype(np.int64)]  # noqa: E731
            cand: dict = {}
            for k, n in zip(key(gp_b), gn_b):
                cand.setdefault(k, []).append(n)
            vk = key(co)
            kmax = max(len(v) for v in cand.values())
            C = np.zeros((len(co), kmax, 3))
            missing = 0
            for i, k in enumerate(vk):
                c = cand.get(k)
                if c is None:
                    missing += 1
                    continue
                C[i, :len(c)] = c
            best = (C[lv] * cn[:, None, :]).sum(-1).max(1)
            ang = np.degrees(np.arccos(np.clip(best, -1, 1)))
            normals_rep[ob.name] = {"gltf_normals": True, "max_angle_deg": float(ang.max()),
                                    "unmatched_vertices": missing}
        else:
            pn = np.empty(len(me.polygons) * 3)
            me.polygons.foreach_get("normal", pn)
            pn = pn.reshape(-1, 3)
            ls = np.empty(len(me.polygons), dtype=np.int64)
            me.polygons.foreach_get("loop_start", ls)
            tot = np.empty(len(me.polygons), dtype=np.int64)
            me.polygons.foreach_get("loop_total", tot)
            face_of_loop = np.repeat(np.arange(len(me.polygons)), tot)
            dots = (cn * pn[face_of_loop]).sum(-1)
            ang = np.degrees(np.arccos(np.clip(dots, -1, 1)))
            normals_rep[ob.name] = {"gltf_normals": False, "flat": True,
                                    "max_angle_deg": float(ang.max())}
        for attr in ("shadow_terminator_geometry_offset", "shadow_terminator_normal_offset",
                     "shadow_terminator_shading_offset"):
            if hasattr(ob, attr):
                setattr(ob, attr, 0.0)
        for attr in ("shadow_terminator_geometry_offset", "shadow_terminator_offset"):
            if hasattr(ob.cycles, attr):
                setattr(ob.cycles, attr, 0.0)
    rep["normals"] = normals_rep

    # ---- materials: Lambertian (Diffuse BSDF, roughness 0) of the scene's albedo
    desc_mats = {m["name"]: m for m in desc["materials"]}
    mats_rep = {}
    gl_by_name = {m.get("name", ""): m for m in gl_mats}
    for mat in bpy.data.materials:
        if mat.users == 0:
            continue
        gm = gl_by_name[mat.name]
        pbr = gm.get("pbrMetallicRoughness", {})
        factor = [float(x) for x in pbr.get("baseColorFactor", [1, 1, 1, 1])[:3]]
        image = None
        im = desc_mats[mat.name]
        if "baseColorTexture" in pbr and "texture" in im:
            tex_nodes = [n for n in mat.node_tree.nodes if n.bl_idname == "ShaderNodeTexImage"]
            assert len(tex_nodes) == 1, (mat.name, tex_nodes)
            image = tex_nodes[0].image
        entry = {"factor": factor}
        if image is not None:
            assert "texture" in im, f"{mat.name}: the scene has no texture"
            assert np.allclose(factor, im["albedo_factor"], atol=1e-6)
            px = np.empty(image.size[0] * image.size[1] * image.channels, dtype=np.float32)
            image.pixels.foreach_get(px)
            px = px.reshape(-1, image.channels)[:, :3].astype(np.float64)
            lin = np.where(px <= 0.04045, px / 12.92, ((px + 0.055) / 1.055) ** 2.4)
            entry.update(image=image.name, size=list(image.size),
                         colorspace=image.colorspace_settings.name,
                         mean_linear=lin.mean(0).tolist(),
                         scene_mean_linear=im["texture"]["mean_linear"])
            image.colorspace_settings.name = "sRGB"
        else:
            # the scene's constant albedo, which includes a sidecar Constant override
            # (an image override, i.e. a texture the glTF does not have, is not supported)
            assert "albedo" in im, f"{mat.name}: the sidecar gives a texture the glTF lacks"
            entry["scene_albedo"] = im["albedo"]
            factor = [float(x) for x in im["albedo"]]
        nt = mat.node_tree
        nt.nodes.clear()
        out = nt.nodes.new("ShaderNodeOutputMaterial")
        out.target = "ALL"
        bsdf = nt.nodes.new("ShaderNodeBsdfDiffuse")
        bsdf.inputs["Roughness"].default_value = 0.0
        if image is None:
            bsdf.inputs["Color"].default_value = (*factor, 1.0)
        else:
            uv = nt.nodes.new("ShaderNodeUVMap")
            uv.uv_map = "UVMap"
            tex = nt.nodes.new("ShaderNodeTexImage")
            tex.image = image
            tex.interpolation = "Linear"
            tex.extension = "REPEAT"
            tex.projection = "FLAT"
            nt.links.new(uv.outputs["UV"], tex.inputs["Vector"])
            mul = nt.nodes.new("ShaderNodeVectorMath")
            mul.operation = "MULTIPLY"
            mul.inputs[1].default_value = factor
            nt.links.new(tex.outputs["Color"], mul.inputs[0])
            nt.links.new(mul.outputs["Vector"], bsdf.inputs["Color"])
        nt.links.new(bsdf.outputs["BSDF"], out.inputs["Surface"])
        mats_rep[mat.name] = entry
    rep["materials"] = mats_rep
    # Lights: removed (the envmap check), or kept as the importer made them
    # (check_blender_lights.py): recorded, then made the glTF's punctual lights
    # (radius 0: a new Blender light gets 0.25 m, which the importer leaves), or
    # with "radius_from_extras" the sphere lightprobe's export describes (the
    # importer keeps a light's glTF extras as custom properties).
    rep["lights"] = {}
    for ob in [o for o in scene.objects if o.type == "LIGHT"]:
        if not job.get("keep_lights"):
            bpy.data.objects.remove(ob)
            continue
        li = ob.data
        rep["lights"][ob.name] = {
            "type": li.type, "energy_W": li.energy, "color": list(li.color),
            "location": list(ob.matrix_world.translation),
            "imported_radius": li.shadow_soft_size,
            "extras_radius": float(li["radius"]) if "radius" in li else None}
        li.shadow_soft_size = (float(li["radius"]) if job.get("radius_from_extras")
                               and "radius" in li else 0.0)
        if hasattr(li, "use_soft_falloff"):
            li.use_soft_falloff = False
    lamps = [(o, o.data.energy, o.location.copy()) for o in scene.objects if o.type == "LIGHT"]

    # ---- render settings
    r = scene.render
    r.engine = "CYCLES"
    cy = scene.cycles
    cy.device = "CPU"
    cy.samples = 16
    cy.use_adaptive_sampling = False
    cy.use_denoising = False
    scene.view_layers[0].cycles.use_denoising = False
    cy.use_animated_seed = False
    cy.sampling_pattern = "TABULATED_SOBOL"
    cy.max_bounces = job["max_bounces"]
    cy.diffuse_bounces = job["max_bounces"]
    cy.glossy_bounces = cy.transmission_bounces = cy.volume_bounces = 0
    cy.caustics_reflective = cy.caustics_refractive = False
    cy.sample_clamp_direct = cy.sample_clamp_indirect = 0.0
    cy.blur_glossy = 0.0
    cy.light_sampling_threshold = 0.0
    cy.use_guiding = False
    cy.use_fast_gi = False
    cy.pixel_filter_type = "BOX"
    cy.filter_width = 1.0
    cy.film_exposure = 1.0
    r.film_transparent = True
    r.use_persistent_data = True
    r.threads_mode = "FIXED"
    r.threads = int(job["threads"])
    r.use_compositing = False
    r.use_sequencer = False
    r.resolution_percentage = 100
    r.pixel_aspect_x = r.pixel_aspect_y = 1.0
    scene.view_settings.view_transform = "Standard"
    scene.view_settings.look = "None"
    scene.view_settings.exposure = 0.0
    scene.view_settings.gamma = 1.0
    im = r.image_settings
    im.file_format = "OPEN_EXR"
    im.color_mode = "RGBA"
    im.color_depth = "32"
    im.exr_codec = "ZIP"

    world = bpy.data.worlds.new("lp_envmap")
    scene.world = world
    world.use_nodes = True
    wn = world.node_tree
    wn.nodes.clear()
    env = wn.nodes.new("ShaderNodeTexEnvironment")
    env.projection = "EQUIRECTANGULAR"
    env.interpolation = job.get("env_interpolation", "Linear")   # (Closest: experiments only)
    bg = wn.nodes.new("ShaderNodeBackground")
    bg.inputs["Strength"].default_value = 1.0
    wout = wn.nodes.new("ShaderNodeOutputWorld")
    wn.links.new(env.outputs["Color"], bg.inputs["Color"])
    wn.links.new(bg.outputs["Background"], wout.inputs["Surface"])
    world.cycles.sampling_method = "MANUAL"
    loaded: dict = {"path": None, "image": None}

    def use_envmap(path: str) -> None:
        if loaded["path"] == path:
            return
        img = bpy.data.images.load(path, check_existing=False)
        img.colorspace_settings.name = "Linear Rec.709"
        env.image = img
        world.cycles.sample_map_resolution = img.size[0]
        if loaded["image"] is not None:
            bpy.data.images.remove(loaded["image"])
        loaded.update(path=path, image=img)

    rep["settings"] = {
        "max_bounces": cy.max_bounces, "diffuse_bounces": cy.diffuse_bounces,
        "sampling_pattern": cy.sampling_pattern, "filter": [cy.pixel_filter_type, cy.filter_width],
        "film_transparent": r.film_transparent, "view_transform": scene.view_settings.view_transform,
        "threads": r.threads, "light_tree": cy.use_light_tree}

    def render(path: str) -> float:
        t = time.time()
        r.filepath = path
        bpy.ops.render.render(write_still=True)
        if not Path(path).is_file():
            raise RuntimeError(f"Blender did not write {path}")
        return time.time() - t

    timings = []
    # ---- C / D renders
    r.resolution_x, r.resolution_y = desc["settings"]["width"], desc["settings"]["height"]
    for job_r in job["renders"]:
        for ob, energy, loc in lamps:        # (a self-test mis-scales or moves them)
            ob.data.energy = energy * float(job_r.get("energy_scale", 1.0))
            ob.location = loc + Vector(g2b(job_r.get("light_offset", [0.0, 0.0, 0.0])))
        if job_r["envmap"] is None:          # lights only: a black World
            bg.inputs["Strength"].default_value = 0.0
        else:
            bg.inputs["Strength"].default_value = 1.0
            use_envmap(job_r["envmap"])
        scene.camera = cams[job_r["view"]]
        cy.seed = int(job_r["seed"])
        cy.samples = int(job_r["spp"])
        mb = int(job_r.get("max_bounces", job["max_bounces"]))
        cy.max_bounces = cy.diffuse_bounces = mb
        timings.append({"out": job_r["out"], "seconds": render(job_r["out"])})
        print(f"[blender] {Path(job_r['out']).name}: {timings[-1]['seconds']:.1f} s", flush=True)

    # ---- B.2 lookup: the bare World through 6 cube-face cameras
    if job.get("lookups"):
        for ob in scene.objects:
            if ob.type == "MESH":
                ob.hide_render = True
        r.film_transparent = False
        r.resolution_x = r.resolution_y = CUBE_RES
        cy.samples = CUBE_SPP
        cy.seed = 0
        cdata = bpy.data.cameras.new("lookup")
        cdata.type = "PERSP"
        cdata.sensor_fit = "VERTICAL"
        cdata.angle_y = math.pi / 2
        cob = bpy.data.objects.new("lookup", cdata)
        scene.collection.objects.link(cob)
        scene.camera = cob
        for lk in job["lookups"]:
            use_envmap(lk["envmap"])
            for name, fwd, up in cube_faces():
                right = np.cross(fwd, up)
                cob.matrix_world = cam_matrix({"right": right, "up": up, "forward": fwd,
                                               "origin": [0, 0, 0]})
                out = str(Path(lk["out_prefix"]).with_name(Path(lk["out_prefix"]).name + f"_{name}.exr"))
                timings.append({"out": out, "seconds": render(out)})
    rep["timings"] = timings
    rep["seconds"] = time.time() - t0
    Path(job["report"]).write_text(json.dumps(rep, indent=2))
    return 0


# ==========================================================================
# Orchestrator (runs under the main .venv)
# ==========================================================================

def blender_cells(grid, width: int, u_shift: float = 0.0) -> np.ndarray:
    """(H, W) ring-cell index under each pixel centre of a lat-long image in
    Blender's World convention, written from the mapping measured in Blender
    (measured): column j at u = (j+0.5)/W = 0.5 + atan2(g.z, g.x)/2pi, row i
    at theta = (i+0.5)pi/H from +Y (glTF axes). Directions are rounded to f32
    as lightprobe's export does before the lookup."""
    h = width // 2
    theta = (np.arange(h) + 0.5) * math.pi / h
    a = 2 * math.pi * ((np.arange(width) + 0.5 + u_shift) / width - 0.5)
    st, ct = np.sin(theta)[:, None], np.cos(theta)[:, None]
    d = np.stack(np.broadcast_arrays(st * np.cos(a)[None], ct, st * np.sin(a)[None]), -1)
    d = d.astype(np.float32).astype(np.float64)
    return grid.cell_of_dirs(d)


def cube_pixel_dirs(fwd, up, res: int, sub: np.ndarray) -> np.ndarray:
    """glTF directions through points of each pixel of a 90-deg cube-face
    camera (row 0 = top). sub: (K, 2) offsets in pixel units from the pixel's
    top-left corner. Returns (res, res, K, 3)."""
    f = np.asarray(fwd, float)
    u = np.asarray(up, float)
    r = np.cross(f, u)
    j = np.arange(res)[None, :, None] + sub[None, None, :, 0]
    i = np.arange(res)[:, None, None] + sub[None, None, :, 1]
    x = 2 * j / res - 1
    y = 1 - 2 * i / res
    d = x[..., None] * r + y[..., None] * u + f
    return d / np.linalg.norm(d, axis=-1, keepdims=True)


# candidate direction transforms for diagnosing a wrong export (glTF axes)
def _rot_y(deg):
    a = math.radians(deg)
    return np.array([[math.cos(a), 0, math.sin(a)], [0, 1, 0], [-math.sin(a), 0, math.cos(a)]])


DIAG_TRANSFORMS = {
    "identity": np.eye(3),
    "azimuth +90 deg": _rot_y(90), "azimuth 180 deg": _rot_y(180), "azimuth -90 deg": _rot_y(-90),
    "mirror x": np.diag([-1.0, 1, 1]), "mirror z": np.diag([1.0, 1, -1]),
    "flip y": np.diag([1.0, -1, 1]),
}
for _k in (90, 180, -90):
    DIAG_TRANSFORMS[f"mirror x then azimuth {_k:+d}"] = _rot_y(_k) @ np.diag([-1.0, 1, 1])


def lookup_check(prefix: Path, grid, radiance: np.ndarray, read_rgb) -> dict:
    """Compare the 6 cube-face renders of the bare World with the ring grid."""
    k = 4
    g = (np.arange(k) + 0.5) / k
    sub = np.stack(np.meshgrid(np.r_[-0.1, g, 1.1], np.r_[-0.1, g, 1.1]), -1).reshape(-1, 2)
    centre = np.array([[0.5, 0.5]])
    got_all, dirs_all, clean_all = [], [], []
    for name, fwd, up in cube_faces():
        img = read_rgb(Path(str(prefix) + f"_{name}.exr"))
        d_sub = cube_pixel_dirs(fwd, up, CUBE_RES, sub)
        cells = grid.cell_of_dirs(d_sub)
        clean = (cells == cells[..., :1]).all(-1)
        got_all.append(img.reshape(-1, 3))
        dirs_all.append(cube_pixel_dirs(fwd, up, CUBE_RES, centre)[:, :, 0].reshape(-1, 3))
        clean_all.append(clean.ravel())
    got = np.concatenate(got_all).astype(np.float64)
    dirs = np.concatenate(dirs_all)
    clean = np.concatenate(clean_all)
    rad = radiance.astype(np.float64)

    def n_match(T):
        want = rad[grid.cell_of_dirs(dirs @ T.T)]
        ok = (np.abs(got - want) <= 1e-4 * np.abs(want) + 1e-6).all(-1)
        return int(ok[clean].sum()), want

    n_id, want = n_match(np.eye(3))
    err = np.abs(got - want)[clean]
    res = {"pixels": int(clean.size), "clean_pixels": int(clean.sum()),
           "matching": n_id, "max_rel_err": float((err / (np.abs(want[clean]) + 1e-6)).max()),
           "pass": n_id == int(clean.sum())}
    if not res["pass"]:
        scores = {name: n_match(T)[0] / clean.sum() for name, T in DIAG_TRANSFORMS.items()}
        res["diagnosis"] = dict(sorted(scores.items(), key=lambda kv: -kv[1]))
    return res


def main() -> int:
    sys.path.insert(0, str(HERE))
    import check_mitsuba as cm
    import lpcheck_common as lc
    import ring_grid as rg
    from check_mitsuba_envmap import BRIGHT_CELLS, RINGS

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scene", type=Path, default=lc.DEFAULT_SCENE)
    ap.add_argument("--bin", type=Path, default=lc.DEFAULT_LIGHTPROBE, help="lightprobe binary")
    ap.add_argument("--blender-python", type=Path, default=DEFAULT_BLENDER_PY,
                    help="python of the venv with bpy (scripts/setup-blender-venv.sh)")
    ap.add_argument("--spp", type=int, default=None, help="default: the sidecar's")
    ap.add_argument("--seed2", type=int, default=2, help="lightprobe's second seed")
    ap.add_argument("--width", type=int, default=4096, help="exported lat-long width")
    ap.add_argument("--threads", type=int, default=2, help="Blender's render threads")
    ap.add_argument("--workdir", type=Path, default=None, help="default: a new temp dir")
    ap.add_argument("--no-self-test", dest="self_test", action="store_false")
    ap.add_argument("--self-test", dest="self_test", action="store_true", default=True)
    ap.add_argument("--self-test-spp", type=int, default=128)
    ap.add_argument("--no-bounce-test", dest="bounce_test", action="store_false",
                    help="skip the self-test's check of Cycles' max_bounces semantics")
    args = ap.parse_args()
    t_start = time.time()
    work = (args.workdir or Path(tempfile.mkdtemp(prefix="check_blender_"))).resolve()
    work.mkdir(parents=True, exist_ok=True)
    bpy_py = args.blender_python
    if not (bpy_py.is_file() and os.access(bpy_py, os.X_OK)):
        log(f"no Blender venv python at {bpy_py}: run `bash scripts/setup-blender-venv.sh`")
        return 2
    binary = lc.find_lightprobe(args.bin)
    mi = lc._mitsuba()                     # scalar_rgb: EXR reading/writing only
    log(f"workdir {work}")

    def read_rgba(p: Path) -> np.ndarray:
        a, names, _ = lc.read_exr(p)
        if names[:4] != ["R", "G", "B", "A"]:
            raise lc.CheckError(f"{p}: channels {names}, expected R, G, B, A")
        return a.astype(np.float32)

    def read_rgb(p: Path) -> np.ndarray:
        return lc.read_exr(p)[0][..., :3].astype(np.float32)

    def write_rgb(p: Path, a: np.ndarray) -> None:
        mi.Bitmap(np.ascontiguousarray(a[..., :3], dtype=np.float32),
                  mi.Bitmap.PixelFormat.RGB).write(str(p))

    ok = True
    # ---------------- A. grid, export, import ------------------------------
    rg.self_check()
    grid = rg.RingGrid(RINGS)
    radiance = rg.demo_envmap(RINGS, BRIGHT_CELLS)
    env_ron = work / "envmap.ron"
    rg.write_envmap_ron(env_ron, RINGS, radiance)
    log(f"envmap.ron: {RINGS} rings, {grid.n_cells} cells; bright cells "
        + ", ".join(f"ring {r} #{j} {rgb}" for r, j, rgb in BRIGHT_CELLS))
    W = args.width
    exr_b = work / f"envmap_blender_{W}.exr"
    exr_m = work / f"envmap_mitsuba_{W}.exr"
    t = time.time()
    for target, p in (("blender", exr_b), ("mitsuba", exr_m)):
        lc.run([binary, "export-envmap", env_ron, "--out", p, "--width", W, "--target", target,
                "--filter", "box"], f"export-envmap --target {target}")
    t_export = time.time() - t
    exported = read_rgb(exr_b)
    mine = radiance[blender_cells(grid, W)]
    n_diff = int((exported != mine).any(-1).sum()) if exported.shape == mine.shape else -1
    exp_ok = n_diff == 0
    log(f"[A2] export-envmap --target blender --width {W}: {exported.shape[1]}x{exported.shape[0]};"
        f" vs this script's rasterisation in Blender's convention: {n_diff} differing pixels -> "
        f"{'PASS' if exp_ok else 'FAIL'}")
    if not exp_ok and n_diff > 0:
        log(f"     first differing (row, col): {np.argwhere((exported != mine).any(-1))[:5].tolist()}")
    ok &= exp_ok
    back = work / "envmap_reimported.ron"
    lc.run([binary, "import-envmap", exr_b, "--rings", RINGS, "--target", "blender", "--out", back],
           "import-envmap --target blender")
    rb, rad_back = rg.read_envmap_ron(back)
    imp_ok = rb == RINGS and np.array_equal(rad_back, radiance)
    log(f"[A3] import-envmap --target blender --rings {RINGS}: "
        f"{'PASS (exact)' if imp_ok else 'FAIL'}")
    ok &= imp_ok

    # wrong exports for the self-test
    perturbed = {}
    if args.self_test:
        p = work / f"envmap_rot90_{W}.exr"
        write_rgb(p, np.roll(exported, W // 4, axis=1))
        perturbed["rot90"] = (p, "blender export rotated 90 deg in azimuth (columns rolled by W/4)")
        p = work / f"envmap_mirror_{W}.exr"
        write_rgb(p, exported[:, ::-1])
        perturbed["mirror_u"] = (p, "blender export mirrored in azimuth (u -> 1 - u)")
        perturbed["mitsuba_as_blender"] = (exr_m, "lightprobe's --target mitsuba export loaded "
                                                  "as if it were the blender one")
        assert np.array_equal(read_rgb(perturbed["rot90"][0]), np.roll(exported, W // 4, axis=1))

    # ---------------- B/C. renders -------------------------------------------
    import scene_truth
    try:
        desc = scene_truth.described(args.scene, binary, log=log)
    except scene_truth.TruthError as e:
        raise lc.CheckError(str(e)) from e
    if desc["vertex_colors"]:
        raise lc.CheckError(f"{args.scene}: vertex colours (COLOR_0) are not built into the "
                            "Blender scene by this check")
    st = desc["settings"]
    spp = args.spp or st["spp"]
    seed1 = st["seed"]
    if args.seed2 == seed1:
        raise SystemExit("--seed2 must differ from the sidecar's seed")
    views = [c["name"] for c in desc["cameras"]]
    cycles_bounces = st["max_bounces"] - 1
    log(f"scene {args.scene}: {desc['triangles']} triangles, views {views}, "
        f"{st['width']}x{st['height']}, {spp} spp; lightprobe max_bounces {st['max_bounces']} "
        f"-> Cycles max_bounces {cycles_bounces}")

    t = time.time()
    lp_json = {}
    for s in (seed1, args.seed2):
        proc = lc.run([binary, "render-reference", args.scene, "--envmap", env_ron,
                       "--no-sphere-lights", "--out", work / f"lp_seed{s}", "--quiet", "--json",
                       "--seed", s, "--spp", spp], "lightprobe render-reference")
        lp_json[s] = json.loads(proc.stdout)
        if lp_json[s].get("lights"):
            raise lc.CheckError("lightprobe rendered sphere lights despite --no-sphere-lights")
    t_lp = time.time() - t

    bdir = work / "blender"
    bdir.mkdir(exist_ok=True)
    renders = []
    for v in views:
        for s in (0, 1):
            renders.append({"envmap": str(exr_b), "view": v, "seed": s, "spp": spp,
                            "out": str(bdir / f"{v}_seed{s}.exr")})
    st_spp = args.self_test_spp
    if args.self_test:
        for name, (p, _) in [("control", (exr_b, ""))] + list(perturbed.items()):
            for v in views:
                for s in (20, 21):
                    renders.append({"envmap": str(p), "view": v, "seed": s, "spp": st_spp,
                                    "out": str(bdir / f"selftest_{name}_{v}_seed{s}.exr")})
    args.bounce_test = args.bounce_test and args.self_test
    if args.bounce_test:
        for v in views:
            for s in (30, 31):
                renders.append({"envmap": str(exr_b), "view": v, "seed": s, "spp": st_spp,
                                "max_bounces": 0, "out": str(bdir / f"bounces0_{v}_seed{s}.exr")})
                renders.append({"envmap": str(exr_b), "view": v, "seed": s, "spp": st_spp,
                                "max_bounces": cycles_bounces + 1,
                                "out": str(bdir / f"bounces{cycles_bounces + 1}_{v}_seed{s}.exr")})
    lookups = [{"envmap": str(exr_b), "out_prefix": str(bdir / "lookup_blender")}]
    for name, (p, _) in perturbed.items():
        lookups.append({"envmap": str(p), "out_prefix": str(bdir / f"lookup_{name}")})
    job = {"gltf": str(lc.gltf_path_from_sidecar(args.scene).resolve()), "desc": desc,
           "max_bounces": cycles_bounces, "threads": args.threads, "renders": renders,
           "lookups": lookups, "report": str(work / "blender_report.json")}
    job_p = work / "blender_job.json"
    job_p.write_text(json.dumps(job, indent=1))
    t = time.time()
    blog = work / "blender.log"
    with open(blog, "w") as fh:
        proc = subprocess.run([str(bpy_py), str(Path(__file__).resolve()), "--blender-worker",
                               str(job_p)], stdout=fh, stderr=subprocess.STDOUT,
                              stdin=subprocess.DEVNULL)
    t_bl = time.time() - t
    if proc.returncode != 0:
        log(f"Blender worker failed (exit {proc.returncode}); last lines of {blog}:")
        log("".join(blog.read_text().splitlines(True)[-30:]))
        return 2
    brep = json.loads((work / "blender_report.json").read_text())
    tm = {Path(x["out"]).name: x["seconds"] for x in brep["timings"]}
    t_main = sum(v for k, v in tm.items() if "_seed" in k and not k.startswith(("selftest", "bounces")))
    log(f"rendered: lightprobe 2 seeds x {len(views)} views in {t_lp:.1f} s; Blender "
        f"{brep['blender']} worker {t_bl:.1f} s in all (import {brep['import_seconds']:.1f} s, "
        f"main renders {t_main:.1f} s = {t_main / (2 * len(views)):.1f} s per {spp}-spp view)")

    # ---------------- B.1 set-up facts ----------------------------------------
    setup_ok = True
    for v, c in brep["cameras"].items():
        good = (c.get("imported_matrix_max_diff", 1) < 1e-4
                and abs(c.get("imported_yfov", math.inf) - c["yfov"]) < 1e-6)
        setup_ok &= good
        log(f"[B1] camera {v}: imported glTF camera vs the scene's own reading (scene_truth.py) in Blender axes: "
            f"max matrix diff {c.get('imported_matrix_max_diff', float('nan')):.2e}, yfov "
            f"{c.get('imported_yfov', float('nan')):.6f} vs {c['yfov']:.6f} -> "
            f"{'same' if good else 'DIFFERENT'}")
    worst = max(n["max_angle_deg"] for n in brep["normals"].values())
    nrm_ok = worst < 0.05 and all(n.get("unmatched_vertices", 0) == 0 for n in brep["normals"].values())
    setup_ok &= nrm_ok
    log(f"[B1] normals: Blender corner normals vs glTF NORMAL (flat face normals for "
        f"{[k for k, n in brep['normals'].items() if not n['gltf_normals']]}): max angle "
        f"{worst:.4f} deg -> {'PASS' if nrm_ok else 'FAIL'}")
    for name, m in brep["materials"].items():
        if "image" in m:
            d = np.abs(np.subtract(m["mean_linear"], m["scene_mean_linear"])).max()
            good = d < 1e-4 and m["colorspace"] == "sRGB"
            setup_ok &= good
            log(f"[B1] material {name}: texture {m['image']} {m['size']} colour space "
                f"{m['colorspace']}, mean linear albedo {np.round(m['mean_linear'], 5).tolist()} "
                f"(scene {np.round(m['scene_mean_linear'], 5).tolist()}) x factor "
                f"{m['factor']} -> {'same' if good else 'DIFFERENT'}")
    log(f"[B1] other materials: Diffuse BSDF (roughness 0) of the scene's albedo "
        f"({len(brep['materials']) - 1} materials); Cycles settings {brep['settings']}")
    ok &= setup_ok

    lk = lookup_check(bdir / "lookup_blender", grid, radiance, read_rgb)
    log(f"[B2] Cycles World lookup (6 cube faces, {lk['pixels']} pixels, {lk['clean_pixels']} "
        f"inside one cell): {lk['matching']} show their cell's radiance (max rel err "
        f"{lk['max_rel_err']:.1e}) -> {'PASS' if lk['pass'] else 'FAIL'}")
    if not lk["pass"]:
        log(f"     which transform of the direction would match (fraction of pixels): "
            + ", ".join(f"{k} {v:.1%}" for k, v in list(lk["diagnosis"].items())[:4]))
    ok &= lk["pass"]

    # ---------------- C. compare -------------------------------------------
    results, render_ok, masks, refs = {}, True, {}, {}
    for v in views:
        lp1_p, lp2_p = work / f"lp_seed{seed1}" / f"{v}.exr", work / f"lp_seed{args.seed2}" / f"{v}.exr"
        b0_p, b1_p = bdir / f"{v}_seed0.exr", bdir / f"{v}_seed1.exr"
        lp1, lp2 = read_rgba(lp1_p), read_rgba(lp2_p)
        b0, b1 = read_rgba(b0_p), read_rgba(b1_p)
        mask = lp1[..., 3] > 0
        masks[v], refs[v] = mask, (lp1, lp2)
        m = cm.judge(b0, lp1, lp2, b1, mask, spp)
        scale = cm.heatmap_scale(b0, lp1, mask)
        c_b = cm.lightprobe_compare(binary, b0_p, lp1_p, work / f"heat_{v}_blender_vs_lp.png", scale)
        c_f = cm.lightprobe_compare(binary, lp2_p, lp1_p, work / f"heat_{v}_lp2_vs_lp1.png", scale)
        cm.side_by_side(work / f"side_{v}.png", lp1, b0, mask)
        for mine_v, theirs in ((m["rel_mae"], c_b["rel_mae"]), (m["floor"], c_f["rel_mae"])):
            if abs(mine_v - theirs) > 1e-3 * max(theirs, 1e-9) + 1e-7:
                log(f"  warning: own relMAE {mine_v:.6f} != lightprobe compare {theirs:.6f}")
        m["lightprobe_compare"] = {"blender_vs_lp1": c_b, "lp2_vs_lp1": c_f}
        m["pixels"] = int(mask.sum())
        # escaping camera rays add 0 in both: every pixel no sample of a renderer
        # saw geometry in (its own alpha 0) must be exactly black in that renderer
        bg_lp = float(np.abs(lp1[lp1[..., 3] == 0][:, :3]).max(initial=0.0))
        bg_b = float(np.abs(b0[b0[..., 3] == 0][:, :3]).max(initial=0.0))
        m["background_max"] = {"lightprobe": bg_lp, "blender": bg_b}
        if bg_lp > 0 or bg_b > 0:
            m["fails"].append(f"background not black (lightprobe {bg_lp:.3g}, Blender {bg_b:.3g})")
            m["pass"] = False
        # coverage (alpha) agreement: same geometry seen through the same camera
        a_diff = float(np.abs(b0[..., 3] - lp1[..., 3]).mean())
        a_floor = float(np.abs(lp2[..., 3] - lp1[..., 3]).mean())
        a_floor_b = float(np.abs(b1[..., 3] - b0[..., 3]).mean())
        a_exp = math.sqrt((1 + (a_floor_b / max(a_floor, 1e-12)) ** 2) / 2)
        m["alpha"] = {"mean_abs_diff": a_diff, "floor": a_floor, "floor_blender": a_floor_b,
                      "ratio_over_expected": a_diff / max(a_floor, 1e-12) / a_exp}
        if m["alpha"]["ratio_over_expected"] >= ALPHA_RATIO_MAX:
            m["fails"].append(f"alpha (coverage) ratio/expected {m['alpha']['ratio_over_expected']:.2f}"
                              f" >= {ALPHA_RATIO_MAX}")
            m["pass"] = False
        log(f"\n{v}: {m['pixels']} masked pixels; masked mean RGB lightprobe "
            f"{np.round(lp1[mask][:, :3].mean(0), 5).tolist()}  Blender "
            f"{np.round(b0[mask][:, :3].mean(0), 5).tolist()}")
        log(f"    lightprobe compare: relMAE Blender vs lp {c_b['rel_mae']:.4f}, noise floor lp "
            f"seed {args.seed2} vs {seed1} {c_f['rel_mae']:.4f}, ratio "
            f"{c_b['rel_mae'] / c_f['rel_mae']:.3f}")
        log(f"    background (own alpha 0) max: lightprobe {bg_lp:.3g}, Blender {bg_b:.3g} (both "
            f"must be 0); coverage: mean |alpha Blender - lp| {a_diff:.5f}, floor (lp seeds) "
            f"{a_floor:.5f}, Blender's own {a_floor_b:.5f}, ratio/expected "
            f"{m['alpha']['ratio_over_expected']:.3f}")
        cm.print_metrics(m)
        results[v] = m
        render_ok &= m["pass"]
    ok &= render_ok
    log(f"\nCHECK {'PASS' if ok else 'FAIL'}: lightprobe vs Blender/Cycles under the {RINGS}-ring "
        f"envmap exported with --target blender, {spp} spp (outputs in {work}: side_<view>.png = "
        f"lp | Blender | block diff, heat_*.png)")

    # ---------------- D. self-test ---------------------------------------------
    st_ok, st_res = None, {}
    if args.self_test:
        st_ok = True
        log(f"\nSELF-TEST at {st_spp} spp (Blender seeds 20, 21; reference = lightprobe as above):"
            f" the control must PASS, every wrong export must FAIL in every view")
        for name, what in [("control", "the export as lightprobe wrote it")] + \
                [(k, w) for k, (_, w) in perturbed.items()]:
            failed = []
            st_res[name] = {"what": what, "views": {}}
            for v in views:
                a = read_rgba(bdir / f"selftest_{name}_{v}_seed20.exr")
                b = read_rgba(bdir / f"selftest_{name}_{v}_seed21.exr")
                lp1, lp2 = refs[v]
                m = cm.judge(a, lp1, lp2, b, masks[v], st_spp)
                if name != "control":
                    cm.side_by_side(work / f"selftest_{name}_{v}.png", lp1, a, masks[v])
                log(f"  {name:18s} {v:10s} relMAE {m['rel_mae']:.4f} floor {m['floor']:.4f} "
                    f"ratio {m['ratio']:.3f} (/exp {m['ratio'] / m['ratio_expected']:.3f}) bias "
                    f"{cm.fmt_pct(m['bias'])} block relMAE {m['block']:.4f} (ratio/exp "
                    f"{m['block_ratio'] / m['block_ratio_expected']:.3f}) -> "
                    f"{'PASS' if m['pass'] else 'FAIL'}")
                st_res[name]["views"][v] = {k: m[k] for k in ("rel_mae", "floor", "ratio",
                                                              "ratio_expected", "bias", "block",
                                                              "block_ratio", "block_ratio_expected",
                                                              "pass")}
                if not m["pass"]:
                    failed.append(v)
            if name == "control" and failed:
                log(f"  control FAILED in {failed}: the failures below prove nothing")
                st_ok = False
            elif name != "control":
                lkp = lookup_check(bdir / f"lookup_{name}", grid, radiance, read_rgb)
                st_res[name]["lookup"] = lkp
                diag = list(lkp.get("diagnosis", {}).items())[:1]
                log(f"  {name:18s} lookup test: {lkp['matching']}/{lkp['clean_pixels']} pixels "
                    f"right -> {'PASS (not detected!)' if lkp['pass'] else 'FAIL (detected)'}"
                    + (f"; best explained by '{diag[0][0]}' ({diag[0][1]:.1%})" if diag else ""))
                if len(failed) < len(views) or lkp["pass"]:
                    log(f"  {name} was NOT detected everywhere")
                    st_ok = False

    if args.bounce_test:
        log(f"  bounce count (Blender seeds 30, 31): Cycles max_bounces 0 vs lightprobe "
            f"--max-bounces 1 (direct light only; {spp} spp, seeds {seed1}, {args.seed2}) must "
            f"PASS; Cycles {cycles_bounces + 1} vs lightprobe {st['max_bounces']} must FAIL")
        for s in (seed1, args.seed2):
            lc.run([binary, "render-reference", args.scene, "--envmap", env_ron,
                    "--no-sphere-lights", "--out", work / f"lp_direct_seed{s}", "--quiet",
                    "--seed", s, "--spp", spp, "--max-bounces", 1], "lightprobe direct only")
        for v in views:
            mask = masks[v]
            d1 = read_rgba(work / f"lp_direct_seed{seed1}" / f"{v}.exr")
            d2 = read_rgba(work / f"lp_direct_seed{args.seed2}" / f"{v}.exr")
            for mb, ref in ((0, (d1, d2)), (cycles_bounces + 1, refs[v])):
                a = read_rgba(bdir / f"bounces{mb}_{v}_seed30.exr")
                b = read_rgba(bdir / f"bounces{mb}_{v}_seed31.exr")
                m = cm.judge(a, ref[0], ref[1], b, mask, st_spp)
                lpb = 1 if mb == 0 else st["max_bounces"]
                log(f"  {'bounces' + str(mb):18s} {v:10s} Cycles max_bounces {mb} vs lightprobe "
                    f"{lpb}: relMAE {m['rel_mae']:.4f} ratio/exp "
                    f"{m['ratio'] / m['ratio_expected']:.3f} bias {cm.fmt_pct(m['bias'])} block "
                    f"ratio/exp {m['block_ratio'] / m['block_ratio_expected']:.3f} -> "
                    f"{'PASS' if m['pass'] else 'FAIL'}")
                st_res.setdefault(f"bounces{mb}", {})[v] = {
                    k: m[k] for k in ("rel_mae", "floor", "ratio", "ratio_expected", "bias",
                                      "block", "block_ratio", "block_ratio_expected", "pass")}
                if m["pass"] != (mb == 0):
                    log(f"  Cycles max_bounces {mb} {'FAILED' if mb == 0 else 'was NOT told apart'}"
                        f" in {v}: the bounce-count mapping is not pinned")
                    st_ok = False
    if args.self_test:
        log(f"SELF-TEST {'PASS' if st_ok else 'FAIL'}")

    total = time.time() - t_start
    summary = {"scene": str(args.scene), "spp": spp, "width": W, "rings": RINGS, "pass": ok,
               "export_exact": exp_ok, "import_exact": imp_ok, "lookup": lk,
               "blender": brep, "views": results, "self_test_pass": st_ok, "self_test": st_res,
               "seconds": {"total": total, "export": t_export, "lightprobe": t_lp,
                           "blender_worker": t_bl}}
    (work / "check_blender.json").write_text(json.dumps(summary, indent=2, default=float))
    log(f"\ntotal {total:.1f} s; summary in {work / 'check_blender.json'}")
    return 0 if ok and st_ok is not False else 1


if __name__ == "__main__":
    if len(sys.argv) == 3 and sys.argv[1] == "--blender-worker":
        sys.exit(worker_main(sys.argv[2]))
    sys.exit(main())
