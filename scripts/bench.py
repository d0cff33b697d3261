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
Repetitions alternate lightprobe and Mitsuba so that background load hits
both alike; medians are reported. samples/s = W * H * spp * views / seconds.
Prints a summary and writes one JSON object (to --json OUT if given).

Usage: .venv/bin/python scripts/bench.py [--repeat 3] [--json OUT] [--scene S.ron]
       [--spp N] [--threads N]
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

sys.path.insert(0, str(Path(__file__).resolve().parent))
import mitsuba_scene as ms  # noqa: E402


def run_lightprobe(bin_: Path, scene: Path, out: Path, spp: int, threads: int | None) -> dict:
    cmd = [str(bin_)]
    if threads:
        cmd += ["--threads", str(threads)]
    cmd += ["render-reference", str(scene), "--out", str(out), "--spp", str(spp),
            "--quiet", "--json"]
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
    with tempfile.TemporaryDirectory(prefix="bench_") as tmp:
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
            print(f"  rep {r + 1}/{args.repeat}: lightprobe render {res['render']:.2f} s "
                  f"(process wall {res['wall']:.2f} s), Mitsuba render {mi_render[-1]:.2f} s")

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
    print(f"\nmedian of {args.repeat}:")
    print(f"  lightprobe  {lp_sps / 1e6:8.2f} M samples/s  (render {med(lp_render):.2f} s; "
          f"whole process {lp_sps_wall / 1e6:.2f} M samples/s, {med(lp_wall):.2f} s; "
          f"{lp_threads} threads)")
    print(f"  Mitsuba     {mi_sps / 1e6:8.2f} M samples/s  (render {med(mi_render):.2f} s; "
          f"first render incl. JIT {mi_sps_first / 1e6:.2f} M samples/s, {first_total:.2f} s)")
    print(f"  ratio lightprobe / Mitsuba: {result['ratio_lightprobe_over_mitsuba']:.3f} "
          f"(lightprobe whole process / Mitsuba first render: "
          f"{result['ratio_lightprobe_wall_over_mitsuba_first']:.3f})")
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
