#!/usr/bin/env python3
"""Speed benchmark: lightprobe vs Mitsuba 3 (llvm_ad_rgb) on the same scene.

Renders every view of the sidecar (default: the bundled tabletop, 2 views at
128x96, 512 spp, max_bounces 2) with
  * lightprobe `render-reference` (a new process per repetition): its own
    render time, render.json timings.render_seconds (all views; excludes
    loading and BVH build), and the wall time of the whole process;
  * Mitsuba 3 llvm_ad_rgb, same meshes, cameras, spp and depth (scene from
    scripts/mitsuba_scene.py; path integrator with MIS, no Russian
    roulette). The scene is built once; each view is rendered once untimed
    for JIT warm-up ("first", reported, includes tracing/compiling the
    kernel, which Dr.Jit caches in ~/.drjit), then timed per repetition.
In the same run (unless --no-envmap), the same scene lit by a 21-ring
envmap instead of its sphere lights (written by scripts/ring_grid.py: a dim
sky, 0.05-0.15, plus three bright cells; `render-reference --envmap ENV
--no-sphere-lights`), to show what envmap sampling costs lightprobe:
samples/s under the envmap, under the sphere lights, and their ratio
(envmap / sphere; the goal is close to 1). Mitsuba is also timed under the
same envmap exported with `lightprobe export-envmap --width 1024` (its
`envmap` emitter; the width barely matters for speed).
Repetitions alternate lightprobe and Mitsuba (and sphere and envmap runs) so
that background load hits all alike; medians are reported.
samples/s = W * H * spp * views / seconds.
Prints a summary and writes one JSON object (to --json OUT if given).

Usage: .venv/bin/python scripts/bench.py [--repeat 3] [--json OUT] [--scene S.ron]
       [--spp N] [--threads N] [--no-envmap] [--envmap-rings 21]
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import mitsuba_scene as ms  # noqa: E402
import ring_grid as rg  # noqa: E402


def bench_envmap(rings: int) -> tuple:
    """Dim sky plus three bright cells (sun-like warm, blue, white) at
    different heights; cells of a 21-ring grid are ~9 deg across, hence the
    higher radiance than a 9-ring map would need."""
    g = rg.RingGrid(rings)
    pick = lambda frac_ring, frac_phi: (round(frac_ring * (rings - 1)),  # noqa: E731
                                        int(frac_phi * g.counts[round(frac_ring * (rings - 1))]))
    bright = [(*pick(0.25, 0.70), (60.0, 50.0, 40.0)),      # theta ~45 deg
              (*pick(0.40, 0.20), (15.0, 25.0, 50.0)),      # theta ~72 deg
              (*pick(0.15, 0.45), (20.0, 20.0, 20.0))]      # theta ~27 deg
    return rg.demo_envmap(rings, bright), bright


def run_lightprobe(bin_: Path, scene: Path, out: Path, spp: int, threads: int | None,
                   extra: list | None = None) -> dict:
    cmd = [str(bin_)]
    if threads:
        cmd += ["--threads", str(threads)]
    cmd += ["render-reference", str(scene), "--out", str(out), "--spp", str(spp),
            "--quiet", "--json"] + [str(x) for x in (extra or [])]
    for _ in range(20):                 # the binary may vanish briefly during a rebuild
        if bin_.exists():
            break
        time.sleep(3)
    t0 = time.perf_counter()
    r = subprocess.run(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    wall = time.perf_counter() - t0
    if r.returncode != 0:
        raise RuntimeError(f"{' '.join(cmd)} failed ({r.returncode}):\n{r.stderr}")
    rj = json.loads(r.stdout)
    return {"wall": wall, "render": rj["timings"]["render_seconds"], "json": rj}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scene", type=Path, default=ms.DEFAULT_SCENE)
    ap.add_argument("--bin", type=Path, default=ms.DEFAULT_BIN, help="lightprobe binary")
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--spp", type=int, default=None, help="default: the sidecar's")
    ap.add_argument("--threads", type=int, default=None,
                    help="threads for both (default: all cores, each tool's default)")
    ap.add_argument("--json", type=Path, default=None, help="write the result JSON here")
    ap.add_argument("--no-envmap", dest="envmap", action="store_false",
                    help="skip the envmap-lit runs")
    ap.add_argument("--envmap-rings", type=int, default=21)
    args = ap.parse_args()

    if not ms.install_llvm19():
        print("bench.py needs Mitsuba's llvm_ad_rgb variant (libLLVM 19)", file=sys.stderr)
        return 2
    variant = ms.set_variant(require_llvm=True)
    import drjit as dr
    import mitsuba as mi
    if args.threads:
        dr.set_thread_count(args.threads)

    info = ms.lightprobe_info(args.scene, args.bin)
    st = info["settings"]
    spp = args.spp or st["spp"]
    views = [c["name"] for c in info["cameras"]]
    w, h = st["width"], st["height"]
    samples = w * h * spp * len(views)
    print(f"scene {args.scene}: {info['triangles']} triangles, views {views}, {w}x{h}, "
          f"{spp} spp, max_bounces {st['max_bounces']} -> {samples:,} samples per run; "
          f"{os.cpu_count()} CPUs, load average {os.getloadavg()[0]:.2f}")
    load_before = os.getloadavg()

    # Mitsuba: build once, warm up (JIT) once per view
    meshes = ms.load_meshes(ms.sidecar_gltf(args.scene))
    t0 = time.perf_counter()
    S = ms.build_scene(args.scene, args.bin, spp=spp, info=info, meshes=meshes)
    build_s = time.perf_counter() - t0
    first = {}
    for v in views:
        t0 = time.perf_counter()
        S.render(v, seed=0)               # np.array() inside forces evaluation
        first[v] = time.perf_counter() - t0
    first_total = sum(first.values())
    print(f"Mitsuba {mi.__version__} {variant} ({dr.thread_count()} threads): scene build "
          f"{build_s:.2f} s, first render (incl. JIT) {first_total:.2f} s "
          + ", ".join(f"{v} {s:.2f} s" for v, s in first.items()))

    lp_render, lp_wall, mi_render, lp_threads, lp_views = [], [], [], None, []
    env_lp_render, env_lp_wall, env_lp_views, env_mi_render = [], [], [], []
    env_info = None
    with tempfile.TemporaryDirectory(prefix="bench_") as tmp:
        if args.envmap:
            rad, bright = bench_envmap(args.envmap_rings)
            env_ron = Path(tmp) / f"envmap_{args.envmap_rings}.ron"
            rg.write_envmap_ron(env_ron, args.envmap_rings, rad)
            env_exr = Path(tmp) / "envmap.exr"
            ms.run_lightprobe([str(args.bin), "export-envmap", str(env_ron), "--out",
                               str(env_exr), "--width", "1024"])
            g = rg.RingGrid(args.envmap_rings)
            t0 = time.perf_counter()
            S_env = ms.build_scene(args.scene, args.bin, spp=spp, info=info, meshes=meshes,
                                   envmap=env_exr, sphere_lights=False)
            env_build_s = time.perf_counter() - t0
            env_first = 0.0
            for v in views:
                t0 = time.perf_counter()
                S_env.render(v, seed=0)
                env_first += time.perf_counter() - t0
            env_info = {"rings": args.envmap_rings, "cells": g.n_cells,
                        "bright_cells": [{"ring": r, "index": j, "cell": g.cell(r, j),
                                          "radiance": list(c)} for r, j, c in bright],
                        "sky_radiance_range": [float(rad.min()),
                                               float(np.sort(rad.max(1))[-len(bright) - 1])],
                        "mitsuba_export_width": 1024}
            print(f"envmap: {args.envmap_rings} rings, {g.n_cells} cells, bright cells "
                  + ", ".join(f"ring {r} #{j} {c}" for r, j, c in bright)
                  + f"; Mitsuba envmap scene build {env_build_s:.2f} s, first render "
                  f"{env_first:.2f} s")
        for r in range(args.repeat):
            res = run_lightprobe(args.bin, args.scene, Path(tmp) / f"lp{r}", spp, args.threads)
            lp_render.append(res["render"])
            lp_wall.append(res["wall"])
            lp_threads = res["json"].get("threads")
            lp_views.append({v["view"]: v["seconds"] for v in res["json"]["views"]})
            t0 = time.perf_counter()
            for v in views:
                S.render(v, seed=r + 1)
            mi_render.append(time.perf_counter() - t0)
            line = (f"  rep {r + 1}/{args.repeat}: lightprobe render {res['render']:.2f} s "
                    f"(process wall {res['wall']:.2f} s), Mitsuba render {mi_render[-1]:.2f} s")
            if args.envmap:
                er = run_lightprobe(args.bin, args.scene, Path(tmp) / f"lp_env{r}", spp,
                                    args.threads, ["--envmap", env_ron, "--no-sphere-lights"])
                if er["json"].get("lights") or not er["json"].get("envmap"):
                    raise RuntimeError("the envmap run did not render what was asked: "
                                       f"lights {er['json'].get('lights')}, envmap "
                                       f"{er['json'].get('envmap')}")
                env_lp_render.append(er["render"])
                env_lp_wall.append(er["wall"])
                env_lp_views.append({v["view"]: v["seconds"] for v in er["json"]["views"]})
                t0 = time.perf_counter()
                for v in views:
                    S_env.render(v, seed=r + 1)
                env_mi_render.append(time.perf_counter() - t0)
                line += (f"; envmap: lightprobe {er['render']:.2f} s, Mitsuba "
                         f"{env_mi_render[-1]:.2f} s")
            print(line)

    med = statistics.median
    lp_sps = samples / med(lp_render)
    lp_sps_wall = samples / med(lp_wall)
    mi_sps = samples / med(mi_render)
    mi_sps_first = samples / first_total
    load_after = os.getloadavg()
    result = {
        "scene": str(args.scene),
        "triangles": info["triangles"],
        "width": w, "height": h, "spp": spp, "views": views,
        "max_bounces": st["max_bounces"], "samples_per_run": samples,
        "repeat": args.repeat, "cpus": os.cpu_count(),
        "loadavg_before": load_before, "loadavg_after": load_after,
        "lightprobe": {
            "threads": lp_threads,
            "render_seconds": lp_render, "wall_seconds": lp_wall,
            "view_seconds": lp_views,
            "median_render_seconds": med(lp_render), "median_wall_seconds": med(lp_wall),
            "samples_per_second": lp_sps, "samples_per_second_wall": lp_sps_wall,
        },
        "mitsuba": {
            "version": mi.__version__, "variant": variant, "threads": dr.thread_count(),
            "integrator": "path (MIS), max_depth = max_bounces + 1, no Russian roulette",
            "scene_build_seconds": build_s,
            "first_render_seconds": first_total, "first_render_view_seconds": first,
            "render_seconds": mi_render, "median_render_seconds": med(mi_render),
            "samples_per_second": mi_sps, "samples_per_second_first": mi_sps_first,
        },
        # primary: render time vs warm render time; both exclude scene loading/BVH
        "ratio_lightprobe_over_mitsuba": lp_sps / mi_sps,
        # whole lightprobe process vs Mitsuba's first (JIT-compiling) render
        "ratio_lightprobe_wall_over_mitsuba_first": lp_sps_wall / mi_sps_first,
    }
    if args.envmap:
        env_sps = samples / med(env_lp_render)
        env_mi_sps = samples / med(env_mi_render)
        result["envmap"] = env_info
        result["lightprobe_envmap"] = {
            "render_seconds": env_lp_render, "wall_seconds": env_lp_wall,
            "view_seconds": env_lp_views,
            "median_render_seconds": med(env_lp_render),
            "median_wall_seconds": med(env_lp_wall),
            "samples_per_second": env_sps,
            "samples_per_second_wall": samples / med(env_lp_wall),
        }
        result["mitsuba_envmap"] = {
            "scene_build_seconds": env_build_s, "first_render_seconds": env_first,
            "render_seconds": env_mi_render, "median_render_seconds": med(env_mi_render),
            "samples_per_second": env_mi_sps,
        }
        # the goal: envmap sampling must not slow lightprobe much (close to 1)
        result["ratio_lightprobe_envmap_over_sphere"] = env_sps / lp_sps
        result["ratio_mitsuba_envmap_over_sphere"] = env_mi_sps / mi_sps
        result["ratio_lightprobe_over_mitsuba_envmap"] = env_sps / env_mi_sps
    print(f"\nmedian of {args.repeat}:")
    print(f"  lightprobe  {lp_sps / 1e6:8.2f} M samples/s  (render {med(lp_render):.2f} s; "
          f"whole process {lp_sps_wall / 1e6:.2f} M samples/s, {med(lp_wall):.2f} s; "
          f"{lp_threads} threads)")
    print(f"  Mitsuba     {mi_sps / 1e6:8.2f} M samples/s  (render {med(mi_render):.2f} s; "
          f"first render incl. JIT {mi_sps_first / 1e6:.2f} M samples/s, {first_total:.2f} s)")
    print(f"  ratio lightprobe / Mitsuba: {result['ratio_lightprobe_over_mitsuba']:.3f} "
          f"(lightprobe whole process / Mitsuba first render: "
          f"{result['ratio_lightprobe_wall_over_mitsuba_first']:.3f})")
    if args.envmap:
        print(f"  {args.envmap_rings}-ring envmap ({env_info['cells']} cells), no sphere lights:")
        print(f"    lightprobe {env_sps / 1e6:8.2f} M samples/s  (render "
              f"{med(env_lp_render):.2f} s) vs {lp_sps / 1e6:.2f} under the sphere lights: "
              f"envmap / sphere = {result['ratio_lightprobe_envmap_over_sphere']:.3f}")
        print(f"    Mitsuba    {env_mi_sps / 1e6:8.2f} M samples/s  (render "
              f"{med(env_mi_render):.2f} s) vs {mi_sps / 1e6:.2f}: envmap / sphere = "
              f"{result['ratio_mitsuba_envmap_over_sphere']:.3f}; lightprobe / Mitsuba under "
              f"the envmap {result['ratio_lightprobe_over_mitsuba_envmap']:.3f}")
    if load_before[0] > 0.5:
        # (only the load before counts: the benchmark itself adds ~1 per thread)
        print(f"  note: 1-min load average was {load_before[0]:.2f} on {os.cpu_count()} CPUs "
              f"before the run: other work may have slowed both tools (the ratio, from "
              f"interleaved runs, is more robust than the absolute numbers)")
    text = json.dumps(result, indent=2)
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(text + "\n")
        print(f"wrote {args.json}")
    else:
        print(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
