"""Render lightprobe's lighting estimate in Blender (Cycles), each view as lightprobe does.

Written by lightprobe next to the scene it renders. Run it with Blender or the bpy module:

    blender --background --python blender.py [-- --spp N --seed S --views a,b --out DIR --no-render]
    python blender.py [--spp N --seed S --views a,b --out DIR --no-render]      (with `pip install bpy`)

It imports the glTF beside it (the estimate's lights are its KHR_lights_punctual point lights,
their radius in `extras`), then sets up what lightprobe's renderer assumes:
  * every material a Diffuse BSDF of roughness 0 (Lambertian; the importer's Principled BSDF
    adds a specular layer) of colour baseColorFactor x texture x vertex colour, from linear EXR
    textures written beside this script (Cycles would otherwise interpolate sRGB texels before
    decoding them);
  * the World an Environment Texture of envmap_blender.exr (equirectangular, linear, default
    mapping: lightprobe wrote it in Blender's convention), importance-sampled at its width;
  * each light's radius from its extras (the importer gives every light 0.25 m otherwise);
  * Cycles on the CPU: lightprobe's bounce count N counts scattering events, Cycles' Max
    Bounces counts bounces after the first hit, so Cycles gets N - 1; no clamping, caustics,
    denoising, adaptive sampling or path guiding; box pixel filter 1 px wide; transparent film
    (the envmap seen directly is alpha 0, lightprobe renders it black); shadow-terminator
    offsets 0;
  * one camera per view (vertical field of view, lightprobe's image size).
Renders go to renders/<view>.exr (linear float RGBA) unless --no-render; then the scene is set
up and can be saved or looked at (with Blender's UI: `blender --python blender.py -- --no-render`).
"""

import argparse
import json
import sys
from pathlib import Path

import bpy
from mathutils import Matrix, Vector

DATA = {}  # filled in by lightprobe
HERE = Path(__file__).resolve().parent


def blender_axes(v):
    """glTF (+Y up) to Blender (+Z up): (x, y, z) -> (x, -z, y), as Blender's importer does."""
    return Vector((v[0], -v[2], v[1]))


def arguments():
    if "--" in sys.argv:                       # blender --background --python blender.py -- ...
        argv = sys.argv[sys.argv.index("--") + 1:]
    elif sys.argv and Path(sys.argv[0]).resolve() == Path(__file__).resolve():
        argv = sys.argv[1:]                    # python blender.py ...
    else:
        argv = []
    def positive(text):
        if not text.isdigit() or int(text) < 1:
            raise argparse.ArgumentTypeError(f"expected a whole number >= 1, got {text!r}")
        return int(text)

    p = argparse.ArgumentParser(prog="blender.py", description=__doc__.splitlines()[0])
    p.add_argument("--spp", type=positive, default=DATA["spp"], help="samples per pixel")
    p.add_argument("--views", default=None, help="comma-separated views (default: all)")
    p.add_argument("--out", type=Path, default=HERE / "renders", help="folder of the renders")
    p.add_argument("--no-render", action="store_true", help="set the scene up, render nothing")
    p.add_argument("--seed", type=int, default=0, help="Cycles' seed (0 to 2^31 - 1)")
    p.add_argument("--threads", type=positive, default=None, help="render threads (default: all)")
    args = p.parse_args(argv)
    if args.out.exists() and not args.out.is_dir():
        p.error(f"--out {args.out} is a file, not a folder")
    return args


def set_materials():
    # Primitives without a material: glTF's default, which lightprobe renders white.
    default = DATA["materials"].get("")
    if default is not None:
        for ob in bpy.data.objects:
            if ob.type == "MESH" and not any(s.material for s in ob.material_slots):
                mat = bpy.data.materials.get("lightprobe_default") or bpy.data.materials.new(
                    "lightprobe_default")
                mat.use_nodes = True
                DATA["materials"]["lightprobe_default"] = default
                ob.data.materials.clear()
                ob.data.materials.append(mat)
    for mat in bpy.data.materials:
        spec = DATA["materials"].get(mat.name)
        if spec is None or mat.node_tree is None:
            if mat.users:
                print(f"blender.py: warning: material {mat.name!r} is not one lightprobe "
                      "knows by that name; it is left as imported", file=sys.stderr)
            continue
        users = [o for o in bpy.data.objects if o.type == "MESH" and mat.name in o.data.materials]
        colors = {o.data.color_attributes[0].name for o in users if len(o.data.color_attributes)}
        nt = mat.node_tree
        nt.nodes.clear()
        out = nt.nodes.new("ShaderNodeOutputMaterial")
        bsdf = nt.nodes.new("ShaderNodeBsdfDiffuse")
        bsdf.inputs["Roughness"].default_value = 0.0
        color = None
        if spec["texture"]:
            img = bpy.data.images.load(str(HERE / spec["texture"]), check_existing=True)
            img.colorspace_settings.name = "Linear Rec.709"
            tex = nt.nodes.new("ShaderNodeTexImage")
            tex.image, tex.interpolation, tex.extension = img, "Linear", "REPEAT"
            uv = nt.nodes.new("ShaderNodeUVMap")
            nt.links.new(uv.outputs["UV"], tex.inputs["Vector"])
            color = tex.outputs["Color"]
        if len(colors) == 1:
            attr = nt.nodes.new("ShaderNodeAttribute")
            attr.attribute_name = colors.pop()
            if color is None:
                color = attr.outputs["Color"]
            else:
                mul = nt.nodes.new("ShaderNodeVectorMath")
                mul.operation = "MULTIPLY"
                nt.links.new(color, mul.inputs[0])
                nt.links.new(attr.outputs["Color"], mul.inputs[1])
                color = mul.outputs["Vector"]
        factor = spec["color"]
        if color is None:
            bsdf.inputs["Color"].default_value = (*factor, 1.0)
        else:
            scale = nt.nodes.new("ShaderNodeVectorMath")
            scale.operation = "MULTIPLY"
            scale.inputs[1].default_value = factor
            nt.links.new(color, scale.inputs[0])
            nt.links.new(scale.outputs["Vector"], bsdf.inputs["Color"])
        nt.links.new(bsdf.outputs["BSDF"], out.inputs["Surface"])


def set_world(scene):
    world = bpy.data.worlds.new("lightprobe_envmap")
    scene.world = world
    if world.node_tree is None:                # (Blender 5 gives new worlds their nodes)
        world.use_nodes = True
    nt = world.node_tree
    nt.nodes.clear()
    bg = nt.nodes.new("ShaderNodeBackground")
    out = nt.nodes.new("ShaderNodeOutputWorld")
    nt.links.new(bg.outputs["Background"], out.inputs["Surface"])
    if DATA["envmap"] is None:
        bg.inputs["Strength"].default_value = 0.0
        return
    env = nt.nodes.new("ShaderNodeTexEnvironment")
    env.projection, env.interpolation = "EQUIRECTANGULAR", "Linear"
    env.image = bpy.data.images.load(str(HERE / DATA["envmap"]), check_existing=True)
    env.image.colorspace_settings.name = "Linear Rec.709"
    nt.links.new(env.outputs["Color"], bg.inputs["Color"])
    world.cycles.sampling_method = "MANUAL"
    world.cycles.sample_map_resolution = env.image.size[0]


def set_lights():
    for ob in bpy.data.objects:
        if ob.type != "LIGHT":
            continue
        li = ob.data
        li.shadow_soft_size = float(li["radius"]) if "radius" in li else 0.0
        if hasattr(li, "use_soft_falloff"):
            li.use_soft_falloff = False


def set_cycles(scene, args):
    r, cy = scene.render, scene.cycles
    r.engine = "CYCLES"
    cy.device = "CPU"
    cy.samples, cy.seed, cy.use_animated_seed = args.spp, args.seed, False
    cy.use_adaptive_sampling = cy.use_denoising = False
    scene.view_layers[0].cycles.use_denoising = False
    cy.max_bounces = cy.diffuse_bounces = max(DATA["max_bounces"] - 1, 0)
    cy.glossy_bounces = cy.transmission_bounces = cy.volume_bounces = 0
    cy.caustics_reflective = cy.caustics_refractive = False
    cy.sample_clamp_direct = cy.sample_clamp_indirect = 0.0
    cy.blur_glossy = cy.light_sampling_threshold = 0.0
    cy.use_guiding = cy.use_fast_gi = False
    cy.pixel_filter_type, cy.filter_width = "BOX", 1.0
    cy.film_exposure = 1.0
    r.film_transparent = True
    if args.threads:
        r.threads_mode, r.threads = "FIXED", args.threads
    r.use_compositing = r.use_sequencer = False
    r.resolution_percentage = 100
    r.pixel_aspect_x = r.pixel_aspect_y = 1.0
    scene.view_settings.view_transform, scene.view_settings.look = "Standard", "None"
    scene.view_settings.exposure, scene.view_settings.gamma = 0.0, 1.0
    im = r.image_settings
    im.file_format, im.color_mode, im.color_depth, im.exr_codec = "OPEN_EXR", "RGBA", "32", "ZIP"
    for ob in bpy.data.objects:
        for attr in ("shadow_terminator_geometry_offset", "shadow_terminator_normal_offset",
                     "shadow_terminator_shading_offset"):
            if hasattr(ob, attr):
                setattr(ob, attr, 0.0)


def add_camera(scene, view):
    data = bpy.data.cameras.new("lightprobe_" + view["name"])
    data.type, data.sensor_fit, data.angle_y = "PERSP", "VERTICAL", view["yfov"]
    data.clip_start, data.clip_end = 1e-3, 1e4
    ob = bpy.data.objects.new("lightprobe_" + view["name"], data)
    scene.collection.objects.link(ob)
    m = Matrix.Identity(4)
    cols = [blender_axes(view[k]) for k in ("right", "up", "back")] + [blender_axes(view["origin"])]
    for i in range(3):
        for j in range(4):
            m[i][j] = cols[j][i]
    ob.matrix_world = m
    return ob


def main():
    args = arguments()
    bpy.ops.wm.read_factory_settings(use_empty=True)
    bpy.ops.import_scene.gltf(filepath=str(HERE / DATA["gltf"]))
    scene = bpy.context.scene
    set_materials()
    set_world(scene)
    set_lights()
    set_cycles(scene, args)
    views = DATA["views"]
    if args.views:
        wanted = args.views.split(",")
        unknown = [v for v in wanted if v not in {w["name"] for w in views}]
        if unknown:
            sys.exit(f"blender.py: no view named {', '.join(unknown)}; views: "
                     + ", ".join(v["name"] for v in views))
        views = [v for w in wanted for v in views if v["name"] == w]
    cameras = [(v, add_camera(scene, v)) for v in views]
    if args.no_render:
        return
    args.out.mkdir(parents=True, exist_ok=True)
    for view, cam in cameras:
        scene.camera = cam
        scene.render.resolution_x, scene.render.resolution_y = view["width"], view["height"]
        scene.render.filepath = str(args.out / (view["name"] + ".exr"))
        bpy.ops.render.render(write_still=True)
        print(f"blender.py: {scene.render.filepath}", flush=True)


main()
