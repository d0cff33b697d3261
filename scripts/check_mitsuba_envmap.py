#!/usr/bin/env python3
"""Cross-render check of record for the ring envmap: lightprobe vs Mitsuba 3.

What it does (default: the bundled tabletop, its 2 views, 512 spp):
 A. Grid and export, no rendering (scripts/ring_grid.py is an independent
    Python implementation of the ring grid, written from the spec):
    1. writes a non-trivial 9-ring envmap.ron (dim sky, bluer upward, a little
       per-cell variation, darker ground; a warm bright cell in ring 2 at
       phi = 240 deg (up, front-left: -X, +Z) and a blue bright cell in ring 3
       at phi = 67.5 deg (low, right-back: +X, -Z));
    2. `lightprobe export-envmap --width W` (Mitsuba target, box filter) must
       equal ring_grid's own rasterisation of that file bit for bit;
    3. `lightprobe import-envmap --rings N` of that EXR must give back the
       written values exactly;
    4. Mitsuba's own `envmap` emitter, loading the exported EXR, is evaluated
       at the direction of every pixel centre (u = (j+0.5)/W, theta =
       i*pi/(H-1)); the value must be ring_grid's cell value for that
       direction (to interpolation round-off). This pins the convention to
       well below a pixel: a half-pixel column shift fails it. Also reported:
       Mitsuba's bilinear envmap vs the piecewise-constant grid over 1M
       uniform directions (mean radiance difference and fraction of
       directions that differ, all within ~1 pixel of a cell edge), and the
       exact solid angle each cell gets in Mitsuba's reconstruction.
 B. Renders: lightprobe `render-reference --envmap envmap.ron
    --no-sphere-lights` with the sidecar's seed and --seed2, and Mitsuba
    (scripts/mitsuba_scene.py, `envmap` emitter loading the exported EXR with
    the default to_world, no sphere lights, hide_emitters) with seeds 0 and 1.
 C. Compares each view exactly as scripts/check_mitsuba.py does (its judge():
    per-channel bias, pixel relMAE ratio vs the noise-only expectation, block
    relMAE ratio and absolute cap) with the same thresholds (justified there
    and re-measured for envmap lighting below). Exit 1 if any view FAILS.
 D. Self-test (unless --no-self-test): the same judge() against Mitsuba
    renders of deliberately wrong exports -- rotated 90 deg in azimuth
    (columns rolled by W/4), mirrored in azimuth (phi -> -phi: the sign bug
    atan2(-x, -z)), flipped vertically (up/down swapped) -- must each FAIL in
    every view, while the unperturbed export at the same spp must PASS (the
    control). A half-pixel column shift (columns at u = j/W: what an export
    that forgot the +0.5 would give) is rendered too but
    only reported: it moves cell edges by 180/W deg (0.04 deg at 4096, 0.18
    deg at 1024), far below what a 128x96 render at these spp can see; the
    lookup test (A.4) must FAIL it instead, and does.

Why W = 4096 (default; --width): Mitsuba interpolates the lat-long image
bilinearly between pixel centres, while lightprobe's envmap is piecewise
constant. With a box export every pixel holds the cell under its centre, so
in Mitsuba each cell edge effectively sits at the midpoint between the two
pixel centres around it: up to half a pixel from the true edge. A.4 computes
the resulting per-cell solid-angle error exactly (and confirms the total by
Monte Carlo on Mitsuba's emitter). It scales as 1/W; for this envmap:
  W = 1024: worst cell (a pole cap) -2.70 %, warm bright cell -0.35 %, whole
            map [-0.19, -0.13, -0.02] % -> renders biased by up to -0.37 %
            (measured; still a PASS, but a third of the 1 % budget);
  W = 4096: worst cell -0.68 %, warm cell -0.09 %, whole map [-0.05, -0.03,
            -0.01] % -- below the seed-to-seed bias (~0.1 %).
Cost at 4096: export 0.6 s, a 100 MB EXR, ~2 s more Mitsuba scene building.
A half-pixel shift is 0.04 deg of azimuth at 4096 (0.18 deg at 1024).

Thresholds: check_mitsuba.py's, re-measured under this envmap (128x96, 2
views, Mitsuba 3.9.1 llvm_ad_rgb, W = 4096; Mitsuba-vs-Mitsuba controls,
4 seeds each as img/img2/ref/ref2, 3 per view and spp):
  512 spp: |bias| <= 0.20 %, pixel ratio/expected 0.998-1.012, block
           ratio/expected 0.985-1.069, block relMAE 0.53-0.62 %;
  128 spp: |bias| <= 0.25 %, pixel ratio/expected 0.983-1.012, block
           ratio/expected 0.887-1.019, block relMAE 0.99-1.13 %;
  lightprobe seeds 1-6 pairwise (512 spp): |bias| <= 0.23 %; the mean of
  lightprobe seeds 1-4 vs the mean of 12 Mitsuba seeds: +0.08 % / +0.05 %
  (cam_front / cam_side, red), i.e. no bias beyond W = 4096's -0.05 %.
So BIAS_MAX 1 % (4-5x the seed spread), PIXEL_RATIO_MAX 1.15 (~10 sd),
BLOCK_RATIO_MAX 1.5 and the 2 % block cap (>= 256 spp) keep a wide margin
for an unbiased render, while every wrong export in the self-test exceeds
them many times over (rot90 / mirror_u: pixel ratio/expected > 3, block
ratio/expected > 12; flip_v: bias -84 %).

Usage:
  .venv/bin/python scripts/check_mitsuba_envmap.py [--scene S.ron] [--spp N]
      [--width W] [--workdir DIR] [--no-self-test] [--self-test-spp N]
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import check_mitsuba as cm  # noqa: E402  (judge(), thresholds, pictures)
import mitsuba_scene as ms  # noqa: E402
import ring_grid as rg  # noqa: E402

RINGS = 9
# (ring, index in ring, linear RGB radiance); 9 rings: ring 2 has 12 cells
# (30 deg apart), ring 3 has 16 (22.5 deg apart)
BRIGHT_CELLS = [(2, 8, (12.0, 9.0, 6.0)),     # theta 45 deg, phi 240 deg: warm, up front-left
                (3, 3, (2.5, 4.0, 10.0))]     # theta 67.5 deg, phi 67.5 deg: blue, low right-back

# wrong exports for the self-test: name -> (description, must the render check FAIL?)
PERTURBATIONS = {
    "rot90": ("export rotated 90 deg in azimuth (columns rolled by W/4)", True),
    "mirror_u": ("azimuth mirrored, phi -> -phi (atan2(-x, -z) sign bug)", True),
    "flip_v": ("vertically flipped (+Y and -Y swapped)", True),
    "half_px": ("columns shifted by half a pixel (u = j/W instead of (j+0.5)/W)", False),
}


def log(msg: str = "") -> None:
    print(msg, flush=True)


def perturbed_export(name: str, img: np.ndarray, grid: rg.RingGrid,
                     radiance: np.ndarray) -> np.ndarray:
    w = img.shape[1]
    if name == "rot90":
        return np.roll(img, w // 4, axis=1)
    if name == "mirror_u":
        return img[:, ::-1]
    if name == "flip_v":
        return img[::-1]
    if name == "half_px":
        return grid.rasterise(radiance, w, u_offset=0.0)
    raise ValueError(name)


# --------------------------------------------------------------------------
# A. grid / export / import / Mitsuba lookup
# --------------------------------------------------------------------------

def mitsuba_envmap_eval(envmap, dirs: np.ndarray) -> np.ndarray:
    """Mitsuba's envmap emitter radiance seen along world directions dirs (N, 3)."""
    import drjit as dr
    import mitsuba as mi
    em = envmap if isinstance(envmap, mi.Emitter) else mi.load_dict(ms.envmap_dict(envmap))
    si = dr.zeros(mi.SurfaceInteraction3f)
    d = np.ascontiguousarray(dirs, dtype=np.float32)
    # eval() looks up -si.wi: wi points from the envmap back into the scene
    si.wi = mi.Vector3f(-d[:, 0], -d[:, 1], -d[:, 2])
    out = np.array(em.eval(si), dtype=np.float64)
    if mi.variant().startswith("scalar"):
        raise RuntimeError("the lookup test needs a vectorised (llvm) variant")
    return out.T if out.shape[0] == 3 and out.shape[-1] != 3 else out.reshape(-1, 3)


def lookup_test(envmap, grid: rg.RingGrid, radiance: np.ndarray, width: int,
                rows_per_chunk: int = 128) -> dict:
    """Mitsuba's envmap at every pixel-centre direction must be the grid's
    cell value for that direction. Tolerance: 1 % of the local contrast (the
    3x3 range of the grid raster there) + 1e-4 relative, which allows float32
    round-off in Mitsuba's u, v (interpolation weights ~1e-3) but not a
    half-pixel shift (weights 0.5). Done in row chunks to bound memory."""
    import mitsuba as mi
    h = width // 2
    theta = np.arange(h) * math.pi / (h - 1)
    phi = 2 * math.pi * (np.arange(width) + 0.5) / width
    rad = radiance.astype(np.float64)
    em = mi.load_dict(ms.envmap_dict(envmap))
    bad_total, max_w, worst, worst_score = 0, 0.0, [0, 0], -1.0
    for r0 in range(0, h, rows_per_chunk):
        r1 = min(h, r0 + rows_per_chunk)
        lo, hi = max(0, r0 - 1), min(h, r1 + 1)          # one halo row each side
        T, P = np.meshgrid(theta[lo:hi], phi, indexing="ij")
        want = rad[grid.cell_of_dirs(rg.RingGrid.dir_of(T, P))]      # (hi-lo, W, 3)
        core = slice(r0 - lo, r0 - lo + (r1 - r0))
        dirs = rg.RingGrid.dir_of(T[core], P[core]).reshape(-1, 3)
        got = mitsuba_envmap_eval(em, dirs).reshape(r1 - r0, width, 3)
        pad = np.concatenate([want[:, -1:], want, want[:, :1]], axis=1)   # azimuth wraps
        if lo == r0:
            pad = np.concatenate([pad[:1], pad], axis=0)
        if hi == r1:
            pad = np.concatenate([pad, pad[-1:]], axis=0)
        stack = np.stack([pad[1 + di:1 + di + (r1 - r0), 1 + dj:1 + dj + width]
                          for di in (-1, 0, 1) for dj in (-1, 0, 1)])
        contrast = stack.max(0) - stack.min(0)
        w_c = want[core]
        err = np.abs(got - w_c)
        bad_total += int((err > 0.01 * contrast + 1e-4 * np.abs(w_c)).any(-1).sum())
        if (contrast > 0).any():
            max_w = max(max_w, float((err[contrast > 0] / contrast[contrast > 0]).max()))
        score = err / (contrast + 1e-4 * np.abs(w_c) + 1e-12)
        k = np.unravel_index(np.argmax(score), score.shape)
        if score[k] > worst_score:
            worst_score, worst = float(score[k]), [int(k[0]) + r0, int(k[1])]
    return {"pixels": h * width, "mismatched_pixels": bad_total,
            "max_error_over_local_contrast": max_w, "worst_pixel_row_col": worst,
            "pass": bad_total == 0}


def reconstructed_solid_angles(grid: rg.RingGrid, width: int, u_offset: float = 0.5) -> np.ndarray:
    """Solid angle each cell gets in Mitsuba's reconstruction of a box export:
    Mitsuba interpolates bilinearly in (u, v) between pixel centres (columns
    at u = (j+0.5)/W, periodic; rows at theta = i*pi/(H-1)), so a pixel's
    weight is (2 pi / W) * integral of its row's hat function times
    sin(theta). A box export puts every pixel in the cell under its centre,
    so each cell edge effectively moves to the midpoint between the pixel
    centres on either side of it (up to half a pixel). Exact, no sampling."""
    h = width // 2
    a = math.pi / (h - 1)
    row_w = np.sin(np.arange(h) * a) * 2 * (1 - math.cos(a)) / a
    row_w[0] = row_w[-1] = 1 - math.sin(a) / a
    cells = grid.latlong_cells(width, u_offset)
    w = np.broadcast_to((2 * math.pi / width) * row_w[:, None], cells.shape)
    return np.bincount(cells.ravel(), weights=w.ravel(), minlength=grid.n_cells)


def random_direction_test(envmap, grid: rg.RingGrid, radiance: np.ndarray, n: int = 1 << 20,
                          seed: int = 5) -> dict:
    """Mitsuba's bilinear envmap vs the piecewise-constant grid over uniform
    directions: relative difference of the mean radiance (what the renders'
    bias sees) and the fraction of directions differing by > 1 %."""
    rng = np.random.default_rng(seed)
    v = rng.normal(size=(n, 3))
    v /= np.linalg.norm(v, axis=1, keepdims=True)
    want = radiance.astype(np.float64)[grid.cell_of_dirs(v)]
    got = mitsuba_envmap_eval(envmap, v)
    differ = (np.abs(got - want) > 0.01 * np.abs(want) + 1e-6).any(-1)
    return {"directions": n, "mean_rel_diff": (got.mean(0) / want.mean(0) - 1).tolist(),
            "fraction_differing": float(differ.mean())}


# --------------------------------------------------------------------------
# B. renders
# --------------------------------------------------------------------------

def render_lightprobe(bin_, scene, envmap: Path, out: Path, spp: int, seed: int) -> dict:
    cmd = [str(bin_), "render-reference", str(scene), "--envmap", str(envmap),
           "--no-sphere-lights", "--out", str(out), "--quiet", "--json",
           "--seed", str(seed), "--spp", str(spp)]
    rj = json.loads(ms.run_lightprobe(cmd))
    # make sure lightprobe rendered what we asked for
    if rj.get("lights"):
        raise SystemExit(f"lightprobe rendered sphere lights despite --no-sphere-lights: {rj['lights']}")
    if (rj.get("envmap") or {}).get("rings") != RINGS:
        raise SystemExit(f"lightprobe's render.json does not show the {RINGS}-ring envmap: "
                         f"{rj.get('envmap')}")
    return rj


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scene", type=Path, default=ms.DEFAULT_SCENE)
    ap.add_argument("--bin", type=Path, default=ms.DEFAULT_BIN, help="lightprobe binary")
    ap.add_argument("--spp", type=int, default=None, help="default: the sidecar's")
    ap.add_argument("--seed2", type=int, default=2, help="lightprobe's second seed")
    ap.add_argument("--width", type=int, default=4096,
                    help="exported lat-long width (see the docstring for why 4096)")
    ap.add_argument("--workdir", type=Path, default=None, help="default: a new temp dir")
    ap.add_argument("--no-self-test", dest="self_test", action="store_false")
    ap.add_argument("--self-test", dest="self_test", action="store_true", default=True,
                    help="run the self-test after the check (default)")
    ap.add_argument("--self-test-spp", type=int, default=128)
    args = ap.parse_args()
    t_start = time.time()
    work = args.workdir or Path(tempfile.mkdtemp(prefix="check_mitsuba_envmap_"))
    work.mkdir(parents=True, exist_ok=True)
    variant = ms.set_variant(require_llvm=True)
    import mitsuba as mi
    log(f"workdir {work}\nMitsuba {mi.__version__} variant {variant}")
    ms.verify_conventions(log)
    ok = True

    # ---------------- A. grid, export, import, Mitsuba lookup -------------
    rg.self_check()
    grid = rg.RingGrid(RINGS)
    log(f"ring_grid: spec counts for N = 2..25 OK; {RINGS} rings -> {grid.n_cells} cells "
        f"{grid.counts.tolist()}; solid angles sum to 4 pi")
    radiance = rg.demo_envmap(RINGS, BRIGHT_CELLS)
    env_ron = work / "envmap.ron"
    rg.write_envmap_ron(env_ron, RINGS, radiance)
    _, radiance_read = rg.read_envmap_ron(env_ron)
    assert np.array_equal(radiance_read, radiance)
    sa = grid.solid_angles()
    log(f"envmap.ron: {grid.n_cells} cells, sky {radiance.min():.3f}..{np.sort(radiance.max(1))[-3]:.3f}, "
        f"bright cells " + ", ".join(f"ring {r} #{j} (cell {grid.cell(r, j)}) {rgb}"
                                      for r, j, rgb in BRIGHT_CELLS)
        + f"; power share of the bright cells "
        f"{(sa[[grid.cell(r, j) for r, j, _ in BRIGHT_CELLS]] * radiance[[grid.cell(r, j) for r, j, _ in BRIGHT_CELLS]].mean(1)).sum() / (sa * radiance.mean(1)).sum():.0%}")

    exr = work / f"envmap_{args.width}.exr"
    ms.run_lightprobe([str(args.bin), "export-envmap", str(env_ron), "--out", str(exr),
                       "--width", str(args.width), "--target", "mitsuba", "--filter", "box"])
    exported, names, fmt = cm_read_rgb(exr)
    mine = grid.rasterise(radiance, args.width)
    n_diff = int((exported != mine).any(-1).sum())
    exp_ok = exported.shape == mine.shape and n_diff == 0
    log(f"[A2] export-envmap --width {args.width}: {exported.shape[1]}x{exported.shape[0]} "
        f"{names} {fmt}; vs ring_grid's rasterisation: {n_diff} differing pixels -> "
        f"{'PASS' if exp_ok else 'FAIL'}")
    if not exp_ok:
        bad = np.argwhere((exported != mine).any(-1))[:5]
        log(f"     first differing pixels (row, col): {bad.tolist()}")
    ok &= exp_ok

    back_ron = work / "envmap_imported.ron"
    ms.run_lightprobe([str(args.bin), "import-envmap", str(exr), "--rings", str(RINGS),
                       "--out", str(back_ron)])
    rings_back, back = rg.read_envmap_ron(back_ron)
    imp_ok = rings_back == RINGS and back.shape == radiance.shape and np.array_equal(back, radiance)
    log(f"[A3] import-envmap --rings {RINGS}: {back.shape[0]} cells, max |diff| "
        f"{np.abs(back - radiance).max() if back.shape == radiance.shape else 'shape mismatch'} "
        f"-> {'PASS (exact)' if imp_ok else 'FAIL'}")
    ok &= imp_ok

    lk = lookup_test(exr, grid, radiance, args.width)
    log(f"[A4] Mitsuba envmap lookup at all {lk['pixels']} pixel-centre directions vs "
        f"ring_grid: {lk['mismatched_pixels']} mismatches (largest error / local contrast "
        f"{lk['max_error_over_local_contrast']:.2e}) -> {'PASS' if lk['pass'] else 'FAIL'}")
    ok &= lk["pass"]
    eff = reconstructed_solid_angles(grid, args.width)
    rel = eff / sa - 1
    bright = [grid.cell(r, j) for r, j, _ in BRIGHT_CELLS]
    recon = ((radiance * eff[:, None]).sum(0) / (radiance * sa[:, None]).sum(0) - 1)
    rd = random_direction_test(exr, grid, radiance)
    rd["reconstruction_power_error"] = recon.tolist()
    rd["max_cell_solid_angle_error"] = float(np.abs(rel).max())
    rd["bright_cell_solid_angle_error"] = rel[bright].tolist()
    log(f"     Mitsuba's bilinear reconstruction of the box export moves cell edges by up to "
        f"half a pixel: cell solid angles off by up to {np.abs(rel).max():.2%} (cell "
        f"{int(np.argmax(np.abs(rel)))}), bright cells {cm.fmt_pct(rel[bright])}; whole envmap "
        f"(radiance x solid angle) {cm.fmt_pct(recon)} exact, {cm.fmt_pct(rd['mean_rel_diff'])} by "
        f"1M uniform directions (+-~0.03 %); {rd['fraction_differing']:.2%} of directions differ "
        f"by > 1 %")
    if np.abs(recon).max() > 0.25 * cm.BIAS_MAX:
        log(f"     warning: at --width {args.width} the export's reconstruction error "
            f"{cm.fmt_pct(recon)} uses up over a quarter of the {cm.BIAS_MAX:.0%} bias budget; "
            f"use a larger --width")

    # ---------------- B. renders ------------------------------------------
    desc = ms.described_scene(args.scene, args.bin)
    st = desc["settings"]
    spp = args.spp or st["spp"]
    seed1 = st["seed"]
    if args.seed2 == seed1:
        raise SystemExit("--seed2 must differ from the sidecar's seed")
    log(f"\nscene {args.scene}: {desc['triangles']} triangles, {len(desc['cameras'])} views, "
        f"{st['width']}x{st['height']}, {spp} spp, max_bounces {st['max_bounces']}; lit by "
        f"envmap.ron only (lightprobe --no-sphere-lights; Mitsuba envmap {exr.name}, default "
        f"to_world, no sphere lights)")
    t = time.time()
    for s in (seed1, args.seed2):
        render_lightprobe(args.bin, args.scene, env_ron, work / f"lp_seed{s}", spp, s)
    t_lp = time.time() - t
    meshes = ms.load_meshes(ms.sidecar_gltf(args.scene))
    t = time.time()
    S = ms.build_scene(args.scene, args.bin, spp=spp, desc=desc, meshes=meshes, envmap=exr,
                       sphere_lights=False)
    (work / "mitsuba").mkdir(exist_ok=True)
    views = [c["name"] for c in desc["cameras"]]
    mi_imgs = {}
    for v in views:
        mi_imgs[v] = (S.render(v, seed=0), S.render(v, seed=1))
        cm.write_exr(work / "mitsuba" / f"{v}.exr", mi_imgs[v][0])
        cm.write_exr(work / "mitsuba" / f"{v}_seed1.exr", mi_imgs[v][1])
    t_mi = time.time() - t
    log(f"rendered: lightprobe 2 seeds in {t_lp:.1f} s, Mitsuba 2 seeds in {t_mi:.1f} s "
        f"(incl. scene build and JIT)")

    # ---------------- C. compare -------------------------------------------
    results, render_ok = {}, True
    masks, lp_refs = {}, {}
    for v in views:
        lp1_p, lp2_p = work / f"lp_seed{seed1}" / f"{v}.exr", work / f"lp_seed{args.seed2}" / f"{v}.exr"
        mi_p = work / "mitsuba" / f"{v}.exr"
        lp1, lp2 = cm.read_exr(lp1_p), cm.read_exr(lp2_p)
        mi0, mi1 = mi_imgs[v]
        mask = lp1[..., 3] > 0
        masks[v], lp_refs[v] = mask, (lp1, lp2)
        m = cm.judge(mi0, lp1, lp2, mi1, mask, spp)
        scale = cm.heatmap_scale(mi0, lp1, mask)
        c_mi = cm.lightprobe_compare(args.bin, mi_p, lp1_p, work / f"heat_{v}_mitsuba_vs_lp.png", scale)
        c_fl = cm.lightprobe_compare(args.bin, lp2_p, lp1_p, work / f"heat_{v}_lp2_vs_lp1.png", scale)
        cm.side_by_side(work / f"side_{v}.png", lp1, mi0, mask)
        for mine_v, theirs in ((m["rel_mae"], c_mi["rel_mae"]), (m["floor"], c_fl["rel_mae"])):
            if abs(mine_v - theirs) > 1e-3 * max(theirs, 1e-9) + 1e-7:
                log(f"  warning: own relMAE {mine_v:.6f} != lightprobe compare {theirs:.6f}")
        m["lightprobe_compare"] = {"mitsuba_vs_lp1": c_mi, "lp2_vs_lp1": c_fl}
        m["pixels"] = int(mask.sum())
        # camera rays that escape must see black in both (lightprobe's default,
        # Mitsuba's hide_emitters): background pixels (lightprobe alpha 0) are 0
        bg_lp = float(np.abs(lp1[~mask][:, :3]).max()) if (~mask).any() else 0.0
        bg_mi = float(np.abs(mi0[~mask][:, :3]).max()) if (~mask).any() else 0.0
        m["background_max"] = {"lightprobe": bg_lp, "mitsuba": bg_mi}
        if bg_lp > 0 or bg_mi > 0:
            m["fails"].append(f"background not black (max lightprobe {bg_lp:.3g}, Mitsuba "
                              f"{bg_mi:.3g}): escaping camera rays see the envmap")
            m["pass"] = False
        log(f"\n{v}: {m['pixels']} masked pixels; masked mean RGB lightprobe "
            f"{np.round(lp1[mask][:, :3].mean(0), 5).tolist()}  Mitsuba "
            f"{np.round(mi0[mask][:, :3].mean(0), 5).tolist()}")
        log(f"    background ({int((~mask).sum())} pixels with lightprobe alpha 0): max "
            f"lightprobe {m['background_max']['lightprobe']:.3g}, Mitsuba "
            f"{m['background_max']['mitsuba']:.3g} (both must be 0)")
        cm.print_metrics(m)
        results[v] = m
        render_ok &= m["pass"]
    ok &= render_ok
    log(f"\nCHECK {'PASS' if ok else 'FAIL'}: lightprobe vs Mitsuba under the {RINGS}-ring "
        f"envmap at {spp} spp, export/import/lookup {'exact' if exp_ok and imp_ok and lk['pass'] else 'WRONG'} "
        f"(outputs in {work}: side_<view>.png = lp | Mitsuba | block diff, heat_*.png)")

    st_ok = None
    st_res = {}
    if args.self_test:
        st_ok, st_res = self_test(args, desc, meshes, masks, lp_refs, exported, grid, radiance, work)
    summary = {"scene": str(args.scene), "spp": spp, "variant": variant, "width": args.width,
               "rings": RINGS, "bright_cells": BRIGHT_CELLS, "pass": ok,
               "export_exact": exp_ok, "import_exact": imp_ok, "lookup": lk,
               "random_directions": rd, "views": results,
               "self_test_pass": st_ok, "self_test": st_res, "seconds": time.time() - t_start}
    (work / "check_mitsuba_envmap.json").write_text(json.dumps(summary, indent=2, default=float))
    log(f"\ntotal {time.time() - t_start:.1f} s; summary in {work / 'check_mitsuba_envmap.json'}")
    return 0 if ok and st_ok is not False else 1


def cm_read_rgb(path: Path):
    """(H, W, 3) float32 as stored, channel names, component format (Mitsuba's
    Bitmap; not lpcheck_common.read_exr, which switches Mitsuba to scalar_rgb)."""
    import mitsuba as mi
    bmp = mi.Bitmap(str(path))
    names = [f.name for f in bmp.struct_()]
    fmt = str(bmp.component_format()).split(".")[-1]
    arr = np.array(bmp, copy=True)
    return arr[..., :3].astype(np.float32), names, fmt


def self_test(args, desc, meshes, masks, lp_refs, exported, grid, radiance, work):
    """Wrong exports rendered by Mitsuba and judged against lightprobe's
    renders with the same judge(); the unperturbed export is the control."""
    spp = args.self_test_spp
    views = list(masks)
    log(f"\nSELF-TEST at {spp} spp (Mitsuba seeds 20, 21; reference = lightprobe seeds as "
        f"above): the control must PASS, rot90 / mirror_u / flip_v must FAIL in every view; "
        f"half_px is reported (render) and must FAIL the lookup test")
    t = time.time()
    good, res = True, {}
    cases = [("control", "unperturbed export (as lightprobe wrote it)", exported, "pass")]
    for name, (what, must_fail) in PERTURBATIONS.items():
        cases.append((name, what, perturbed_export(name, exported, grid, radiance),
                      "fail" if must_fail else "report"))
    for name, what, img, want in cases:
        S = ms.build_scene(args.scene, args.bin, spp=spp, desc=desc, meshes=meshes, envmap=img,
                           sphere_lights=False)
        failed = []
        res[name] = {"what": what, "expect": want, "views": {}}
        for v in views:
            lp1, lp2 = lp_refs[v]
            a, b = S.render(v, seed=20), S.render(v, seed=21)
            m = cm.judge(a, lp1, lp2, b, masks[v], spp)
            if name != "control":
                cm.side_by_side(work / f"selftest_{name}_{v}.png", lp1, a, masks[v])
            log(f"  {name:9s} {v:10s} bias {cm.fmt_pct(m['bias'])} pixel ratio/exp "
                f"{m['ratio'] / m['ratio_expected']:.3f} block ratio/exp "
                f"{m['block_ratio'] / m['block_ratio_expected']:.3f} block relMAE "
                f"{m['block']:.4f} -> {'PASS' if m['pass'] else 'FAIL'}")
            res[name]["views"][v] = {k: m[k] for k in ("bias", "ratio", "ratio_expected",
                                                       "block", "block_ratio",
                                                       "block_ratio_expected", "pass")}
            if not m["pass"]:
                failed.append(v)
        if want == "pass" and failed:
            log(f"  control FAILED in {failed}: at {spp} spp the check rejects the unperturbed "
                f"export, so the failures below prove nothing")
            good = False
        elif want == "fail" and len(failed) < len(views):
            log(f"  perturbation {name} ({what}) was NOT detected in "
                f"{sorted(set(views) - set(failed))}")
            good = False
        elif want == "report":
            log(f"  {name} ({what}): render check {'detects' if failed else 'does NOT detect'} "
                f"it at W = {img.shape[1]} (a half pixel = {180 / img.shape[1]:.2f} deg of azimuth)")
    lk = lookup_test(perturbed_export("half_px", exported, grid, radiance), grid, radiance,
                     exported.shape[1])
    res["half_px"]["lookup"] = lk
    log(f"  half_px   lookup test: {lk['mismatched_pixels']} of {lk['pixels']} pixel-centre "
        f"directions mismatch (largest error / local contrast {lk['max_error_over_local_contrast']:.2f}) "
        f"-> {'PASS (not detected!)' if lk['pass'] else 'FAIL (detected)'}")
    if lk["pass"]:
        good = False
    log(f"SELF-TEST {'PASS' if good else 'FAIL'} ({time.time() - t:.1f} s): "
        + ("the check passes the right export and fails every wrong one"
           if good else "the check cannot be trusted"))
    return good, res


if __name__ == "__main__":
    sys.exit(main())
