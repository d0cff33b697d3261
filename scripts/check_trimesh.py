#!/usr/bin/env python3
"""External-oracle check of lightprobe's scene loading and ray casting, using trimesh + Embree.

1. `lightprobe info SCENE` vs trimesh loading the same glTF (the sidecar's `gltf:`):
   triangle count (exact), bounds (|diff| <= 1e-5), surface area (1e-4 relative), and
   each `info` camera (origin, right, up, forward, yfov) vs the glTF camera node as
   composed by trimesh's scene graph (1e-5).
2. `lightprobe render-reference --spp 1 --aov depth` vs trimesh's Embree ray intersector
   casting the same pixel-centre rays (camera poses and lights from scripts/scene_truth.py's
   own reading of the sidecar and glTF, checked against `lightprobe info`) against the
   world-space mesh (sphere lights intersected analytically: a ray that hits a light
   first reads 0, like lightprobe's depth AOV). Per view:
     - hit/miss agree on >= 99.5 % of pixels,
     - where both hit, |depth_lp - depth_trimesh| <= 1e-4 * depth + 1e-5 on >= 99.5 %,
     - every disagreeing pixel is an edge pixel of the trimesh image (a 3x3 neighbour
       differs in hit/miss, or its depth differs by > 2 %): non-edge disagreements = 0,
     - the depth EXR is W x H (the scene's), float R,G,B with R == G == B, finite, >= 0.
3. Self-test (part of the default run; alone with --self-test): the same comparison
   against deliberately wrong oracle rays (origin moved 2 cm, image flipped vertically,
   rays through pixel corners instead of centres) must FAIL for every view.

Usage: .venv/bin/python scripts/check_trimesh.py [--lightprobe BIN] [--scene SCENE.ron]
                                                   [--workdir DIR] [--self-test | --no-self-test]
Exit status: 0 = all checks passed, 1 = a check failed or could not run.
"""

from __future__ import annotations

import argparse
import json
import shutil
import struct
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from lpcheck_common import (DEFAULT_LIGHTPROBE, DEFAULT_SCENE, CheckError,  # noqa: E402
                            find_lightprobe, gltf_path_from_sidecar, lightprobe_info, log,
                            read_exr, run)
import scene_truth  # noqa: E402

AGREE_MIN = 0.995          # hit/miss agreement and depth-within-tolerance fractions
DEPTH_REL_TOL = 1e-4
DEPTH_ABS_TOL = 1e-5
EDGE_DEPTH_JUMP = 0.02     # a neighbour's depth differing by > 2 % makes a pixel an edge
BOUNDS_TOL = 1e-5
AREA_REL_TOL = 1e-4
SELFTEST_SHIFT = 0.02      # metres
CAMERA_TOL = 1e-5


# ----------------------------------------------------------------------------- geometry

def gltf_json(path: Path) -> dict:
    """The glTF JSON of a .glb (JSON chunk) or .gltf file."""
    data = path.read_bytes()
    if data[:4] == b"glTF":
        jlen, jtype = struct.unpack_from("<I4s", data, 12)
        if jtype != b"JSON":
            raise CheckError(f"{path}: first GLB chunk is not JSON")
        return json.loads(data[20:20 + jlen])
    return json.loads(data)


def load_world_mesh(glb: Path):
    import trimesh
    if not trimesh.ray.has_embree:
        raise CheckError("trimesh has no Embree backend (pip package `embreex` missing); "
                         "run `bash scripts/setup-venv.sh`")
    # process=False: take the file's vertices/faces as they are (no merging/cleanup)
    scene = trimesh.load(str(glb), force="scene", process=False)
    mesh = scene.to_mesh()      # every geometry node with its world transform applied
    return scene, mesh


def camera_rays(cam: dict, mode: str = "centre"):
    """Pixel rays of an `info` camera, row 0 at the top, as (origins, dirs) of shape (H*W, 3)."""
    w, h = int(cam["width"]), int(cam["height"])
    t = np.tan(float(cam["yfov"]) / 2.0)
    off = 0.0 if mode == "corner" else 0.5
    x, y = np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))
    cx = (2.0 * (x + off) / w - 1.0) * t * (w / h)
    cy = (1.0 - 2.0 * (y + off) / h) * t
    right, up, fwd = (np.asarray(cam[k], dtype=np.float64) for k in ("right", "up", "forward"))
    d = cx[..., None] * right + cy[..., None] * up + fwd
    d /= np.linalg.norm(d, axis=-1, keepdims=True)
    d = d.reshape(-1, 3)
    o = np.broadcast_to(np.asarray(cam["origin"], dtype=np.float64), d.shape).copy()
    return o, d


def ray_sphere(o, d, center, radius):
    """Nearest positive hit distance of unit-direction rays with a sphere (inf if none)."""
    oc = o - np.asarray(center, dtype=np.float64)
    b = np.einsum("ij,ij->i", oc, d)
    c = np.einsum("ij,ij->i", oc, oc) - float(radius) ** 2
    disc = b * b - c
    t = np.full(len(o), np.inf)
    ok = disc >= 0
    sq = np.sqrt(np.where(ok, disc, 0.0))
    t0, t1 = -b - sq, -b + sq
    t = np.where(ok & (t0 > 0), t0, np.where(ok & (t1 > 0), t1, np.inf))
    return t


def oracle_depth(mesh, lights, cam, mode="centre", origin_shift=None):
    """trimesh/Embree depth image (0 = no geometry) and the number of light-blocked pixels."""
    w, h = int(cam["width"]), int(cam["height"])
    o, d = camera_rays(cam, mode)
    if origin_shift is not None:
        o = o + origin_shift
    loc, ray_idx, _tri = mesh.ray.intersects_location(o, d, multiple_hits=False)
    t_mesh = np.full(len(d), np.inf)
    t_mesh[ray_idx] = np.linalg.norm(loc - o[ray_idx], axis=1)
    t_light = np.full(len(d), np.inf)
    for L in lights:
        t_light = np.minimum(t_light, ray_sphere(o, d, L["center"], L["radius"]))
    blocked = t_light < t_mesh
    depth = np.where(np.isfinite(t_mesh) & ~blocked, t_mesh, 0.0)
    return depth.reshape(h, w), int((blocked & np.isfinite(t_light)).sum())


# ----------------------------------------------------------------------------- comparison

@dataclass
class ViewResult:
    name: str
    pixels: int
    hit_agree: float
    n_both: int
    depth_ok: float
    max_err: float
    med_err: float
    n_disagree: int
    n_edge: int
    n_nonedge: int
    lp_cov: float
    or_cov: float

    @property
    def passed(self) -> bool:
        return (self.hit_agree >= AGREE_MIN and self.depth_ok >= AGREE_MIN
                and self.n_nonedge == 0)


def edge_mask(depth: np.ndarray) -> np.ndarray:
    """Pixels whose 3x3 neighbourhood has a hit/miss change or a depth jump > 2 %."""
    hit = depth > 0
    h, w = depth.shape
    pd = np.pad(depth, 1, mode="edge")
    ph = np.pad(hit, 1, mode="edge")
    edge = np.zeros_like(hit)
    for dy in (-1, 0, 1):
        for dx in (-1, 0, 1):
            if dx == 0 and dy == 0:
                continue
            nd = pd[1 + dy:1 + dy + h, 1 + dx:1 + dx + w]
            nh = ph[1 + dy:1 + dy + h, 1 + dx:1 + dx + w]
            edge |= nh != hit
            edge |= hit & nh & (np.abs(nd - depth) > EDGE_DEPTH_JUMP * depth)
    return edge


def compare(name: str, lp: np.ndarray, ref: np.ndarray) -> ViewResult:
    """lp: lightprobe depth, ref: oracle (trimesh) depth; both HxW, 0 = no geometry."""
    lp_hit, ref_hit = lp > 0, ref > 0
    agree = lp_hit == ref_hit
    both = lp_hit & ref_hit
    err = np.abs(lp - ref)
    tol = DEPTH_REL_TOL * ref + DEPTH_ABS_TOL
    depth_bad = both & (err > tol)
    disagree = ~agree | depth_bad
    edge = edge_mask(ref)
    e = err[both]
    return ViewResult(
        name=name, pixels=lp.size, hit_agree=float(agree.mean()), n_both=int(both.sum()),
        depth_ok=float(1.0 - depth_bad.sum() / max(both.sum(), 1)),
        max_err=float(e.max()) if e.size else float("nan"),
        med_err=float(np.median(e)) if e.size else float("nan"),
        n_disagree=int(disagree.sum()), n_edge=int((disagree & edge).sum()),
        n_nonedge=int((disagree & ~edge).sum()),
        lp_cov=float(lp_hit.mean()), or_cov=float(ref_hit.mean()))


# ----------------------------------------------------------------------------- steps

def check_stats(info: dict, scene, mesh, glb: Path) -> bool:
    log("== 1. scene statistics and cameras: lightprobe info vs trimesh")
    ok = True
    n_lp, n_tm = int(info["triangles"]), len(mesh.faces)
    good = n_lp == n_tm
    ok &= good
    log(f"  triangles     lightprobe {n_lp:>12d}   trimesh {n_tm:>12d}   "
        f"{'PASS' if good else 'FAIL'} (must be equal)")
    for key, i in (("min", 0), ("max", 1)):
        b_lp = np.asarray(info["bounds"][key], dtype=np.float64)
        b_tm = np.asarray(mesh.bounds[i], dtype=np.float64)
        diff = float(np.abs(b_lp - b_tm).max())
        good = diff <= BOUNDS_TOL
        ok &= good
        fmt = lambda v: "(" + ", ".join(f"{x:+.7f}" for x in v) + ")"  # noqa: E731
        log(f"  bounds.{key}    lightprobe {fmt(b_lp)}   trimesh {fmt(b_tm)}   "
            f"max|diff| {diff:.2e}   {'PASS' if good else 'FAIL'} (<= {BOUNDS_TOL:g})")
    a_lp, a_tm = float(info["surface_area"]), float(mesh.area)
    rel = abs(a_lp - a_tm) / max(abs(a_tm), 1e-30)
    good = rel <= AREA_REL_TOL
    ok &= good
    log(f"  surface area  lightprobe {a_lp:.10f}   trimesh {a_tm:.10f}   "
        f"rel diff {rel:.2e}   {'PASS' if good else 'FAIL'} (<= {AREA_REL_TOL:g})")
    # camera poses: `info` (used for the rays below) vs the glTF camera nodes' world
    # transforms as composed by trimesh's scene graph (glTF camera looks down -Z, +Y up)
    gj = gltf_json(glb)
    for cam in info["cameras"]:
        name = cam["name"]
        try:
            world, _ = scene.graph[name]
        except (KeyError, ValueError):
            log(f"  camera {name:<10s} not a node in the glTF - pose not checked")
            continue
        node = next((n for n in gj.get("nodes", []) if n.get("name") == name), None)
        persp = (gj["cameras"][node["camera"]].get("perspective", {})
                 if node is not None and "camera" in node else {})
        m = np.asarray(world, dtype=np.float64)
        ref = {"origin": m[:3, 3], "right": m[:3, 0], "up": m[:3, 1], "forward": -m[:3, 2]}
        for k in ("right", "up", "forward"):
            ref[k] = ref[k] / np.linalg.norm(ref[k])
        diff = max(float(np.abs(np.asarray(cam[k], dtype=np.float64) - ref[k]).max())
                   for k in ref)
        good = diff <= CAMERA_TOL
        fov_msg = ""
        if "yfov" in persp:
            dfov = abs(float(cam["yfov"]) - float(persp["yfov"]))
            good &= dfov <= 1e-6
            fov_msg = f"   yfov {cam['yfov']:.7f} vs glTF {persp['yfov']:.7f}"
        ok &= good
        log(f"  camera {name:<10s} origin/right/up/forward vs glTF node: max|diff| "
            f"{diff:.2e}{fov_msg}   {'PASS' if good else 'FAIL'} (<= {CAMERA_TOL:g})")
    log(f"  (vertices: lightprobe reports {info.get('vertices')}, trimesh/glTF has "
        f"{len(mesh.vertices)}; not compared - loaders may split/merge vertices)")
    return ok


def load_lp_depth(path: Path, cam: dict) -> tuple[np.ndarray, list[str]]:
    """Depth channel of lightprobe's depth EXR plus a list of format problems."""
    problems = []
    arr, names, fmt = read_exr(path)
    h, w = int(cam["height"]), int(cam["width"])
    if arr.shape[:2] != (h, w):
        problems.append(f"size {arr.shape[1]}x{arr.shape[0]}, expected {w}x{h}")
    if names != ["R", "G", "B"]:
        problems.append(f"channels {names}, expected ['R', 'G', 'B']")
    if fmt.lower() not in ("float32", "float"):
        problems.append(f"component format {fmt}, expected float32")
    if arr.shape[2] >= 3 and not (np.array_equal(arr[..., 0], arr[..., 1])
                                  and np.array_equal(arr[..., 0], arr[..., 2])):
        n = int(((arr[..., 0] != arr[..., 1]) | (arr[..., 0] != arr[..., 2])).sum())
        problems.append(f"R, G, B differ on {n} pixels (expected identical depth)")
    depth = arr[..., 0].astype(np.float64)
    if not np.isfinite(depth).all():
        problems.append(f"{int((~np.isfinite(depth)).sum())} non-finite depth values")
    if (depth < 0).any():
        problems.append(f"{int((depth < 0).sum())} negative depth values")
    return np.nan_to_num(depth, nan=0.0, posinf=0.0, neginf=0.0), problems


def print_view_table(results: list[ViewResult], expect_fail: bool = False) -> None:
    nw = max([4] + [len(r.name) for r in results])
    hdr = (f"  {'view':<{nw}s} {'pixels':>6s} {'lp cov':>7s} {'tm cov':>7s} {'hit/miss':>9s} "
           f"{'both':>6s} {'depth ok':>9s} {'max|dd| m':>10s} {'med|dd| m':>10s} "
           f"{'disagree':>8s} {'edge':>5s} {'nonedge':>7s}  result")
    log(hdr)
    for r in results:
        if expect_fail:
            res = "FAIL as expected" if not r.passed else "PASSED (self-test broken!)"
        else:
            res = "PASS" if r.passed else "FAIL"
        log(f"  {r.name:<{nw}s} {r.pixels:>6d} {100 * r.lp_cov:>6.2f}% {100 * r.or_cov:>6.2f}% "
            f"{100 * r.hit_agree:>8.3f}% {r.n_both:>6d} {100 * r.depth_ok:>8.3f}% "
            f"{r.max_err:>10.3e} {r.med_err:>10.3e} {r.n_disagree:>8d} {r.n_edge:>5d} "
            f"{r.n_nonedge:>7d}  {res}")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--lightprobe", type=Path, default=DEFAULT_LIGHTPROBE,
                    help=f"lightprobe binary (default: {DEFAULT_LIGHTPROBE})")
    ap.add_argument("--scene", type=Path, default=DEFAULT_SCENE,
                    help=f"scene sidecar .ron (default: {DEFAULT_SCENE})")
    ap.add_argument("--workdir", type=Path, default=None,
                    help="where lightprobe renders (default: a temp dir, deleted afterwards)")
    g = ap.add_mutually_exclusive_group()
    g.add_argument("--self-test", action="store_true",
                   help="only run the self-test (perturbed oracle must FAIL)")
    g.add_argument("--no-self-test", action="store_true", help="skip the self-test")
    args = ap.parse_args()
    t_start = time.monotonic()
    try:
        sys.stdout.reconfigure(line_buffering=True)
    except AttributeError:
        pass

    tmp = None
    try:
        binary = find_lightprobe(args.lightprobe.resolve())
        scene_path = args.scene.resolve()
        if not scene_path.is_file():
            raise CheckError(f"scene sidecar not found: {scene_path}")
        if args.workdir is None:
            tmp = tempfile.mkdtemp(prefix="lp_check_trimesh_")
            workdir = Path(tmp)
        else:
            workdir = args.workdir.resolve()
            workdir.mkdir(parents=True, exist_ok=True)

        log(f"lightprobe: {binary}")
        log(f"scene:      {scene_path}")
        info = lightprobe_info(binary, scene_path)
        try:   # the rays below use the scene's own reading, not lightprobe's
            desc = scene_truth.described(scene_path, binary, log=log)
        except scene_truth.TruthError as e:
            raise CheckError(str(e)) from e
        glb = gltf_path_from_sidecar(scene_path)
        if not glb.is_file():
            raise CheckError(f"glTF named by the sidecar not found: {glb}")
        log(f"glTF:       {glb}")
        t0 = time.monotonic()
        _scene, mesh = load_world_mesh(glb)
        log(f"trimesh loaded {len(mesh.faces)} triangles in {time.monotonic() - t0:.2f} s")

        all_ok = True
        if not args.self_test:
            all_ok &= check_stats(info, _scene, mesh, glb)

        # ---- render depth with lightprobe
        log(f"== 2. depth AOV: lightprobe render-reference --spp 1 --aov depth vs "
            f"trimesh/Embree (workdir {workdir})")
        t0 = time.monotonic()
        run([binary, "render-reference", scene_path, "--out", workdir, "--spp", "1",
             "--aov", "depth", "--quiet"], "lightprobe render-reference")
        log(f"  rendered in {time.monotonic() - t0:.2f} s")
        rj_path = workdir / "render.json"
        rj = json.loads(rj_path.read_text()) if rj_path.is_file() else {"views": []}
        depth_files = {v["view"]: Path(v["aov"]["depth"]) for v in rj.get("views", [])
                       if "aov" in v and "depth" in v["aov"]}
        cams = {c["name"]: c for c in desc["cameras"]}
        views = [v["view"] for v in rj.get("views", [])] or list(cams)
        lights = desc.get("lights", [])

        lp_depths, results = {}, []
        for name in views:
            if name not in cams:
                raise CheckError(f"render.json view {name!r} is not a camera of the scene")
            cam = cams[name]
            p = depth_files.get(name, workdir / f"{name}.depth.exr")
            if not p.is_absolute():
                p = workdir / p
            if not p.is_file():
                p2 = workdir / f"{name}.depth.exr"
                if not p2.is_file():
                    raise CheckError(f"depth EXR for view {name} not found ({p})")
                p = p2
            lp, problems = load_lp_depth(p, cam)
            if problems:
                all_ok = False
                for msg in problems:
                    log(f"  FAIL {p.name}: {msg}")
            lp_depths[name] = lp
            if args.self_test:
                continue
            ref, n_blocked = oracle_depth(mesh, lights, cam)
            if n_blocked:
                log(f"  note: {n_blocked} pixels of {name} see a sphere light first "
                    f"(expected depth 0)")
            if lp.shape != ref.shape:
                raise CheckError(f"{name}: depth image {lp.shape} vs camera {ref.shape}")
            results.append(compare(name, lp, ref))
        if results:
            print_view_table(results)
            log(f"  criteria: hit/miss agreement >= {100 * AGREE_MIN:g}%, |dd| <= "
                f"{DEPTH_REL_TOL:g}*depth + {DEPTH_ABS_TOL:g} m on >= {100 * AGREE_MIN:g}% "
                f"of pixels where both hit, 0 non-edge disagreements")
            all_ok &= all(r.passed for r in results)

        # ---- self-test: a wrong oracle must make the comparison fail
        if not args.no_self_test:
            log("== 3. self-test: the comparison must FAIL against deliberately wrong rays")
            perturbations = [
                (f"origin +{SELFTEST_SHIFT * 100:g} cm along camera up",
                 lambda cam: oracle_depth(mesh, lights, cam, origin_shift=SELFTEST_SHIFT
                                          * np.asarray(cam["up"], dtype=np.float64))[0]),
                ("image flipped vertically",
                 lambda cam: oracle_depth(mesh, lights, cam)[0][::-1].copy()),
                ("rays through pixel corners (half-pixel shift)",
                 lambda cam: oracle_depth(mesh, lights, cam, mode="corner")[0]),
            ]
            st_ok = True
            st_results = []
            for label, fn in perturbations:
                for name in views:
                    r = compare(f"{name} / {label}", lp_depths[name], fn(cams[name]))
                    st_results.append(r)
                    st_ok &= not r.passed
            print_view_table(st_results, expect_fail=True)
            log(f"  self-test: {'PASS (every perturbation detected)' if st_ok else 'FAIL'}")
            all_ok &= st_ok

        log(f"RESULT: {'PASS' if all_ok else 'FAIL'}  ({time.monotonic() - t_start:.1f} s)")
        return 0 if all_ok else 1
    except CheckError as e:
        log(f"ERROR: {e}")
        log("RESULT: FAIL (check could not run)")
        return 1
    finally:
        if tmp is not None:
            shutil.rmtree(tmp, ignore_errors=True)


if __name__ == "__main__":
    sys.exit(main())
