#!/usr/bin/env python3
"""How `estimate` scales with the image size and the ring count: whole-command time, fit time
(transport + solve), transport bytes and peak memory, and the transport's cost against a plain
render of the same samples (the estimate's envmap, rendered at the transport's spp, on the same
binary in the same run): at one spp per size, and per sample (`per_sample`: the slopes of both
times over several spp, which leave out what the transport spends per pixel whatever its
samples).

The bundled scene's two views at each size, references rendered at --ref-spp, the estimate at
--spp. Standard library only.

    python3 scripts/bench_scaling.py [--bin target/release/lightprobe] [--out docs/bench/scaling.json]
"""

import argparse
import json
import os
import re
import subprocess
import sys
import tempfile
import time

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def peak_kib(cmd):
    """Runs cmd under /usr/bin/time -v; returns (seconds, peak RSS in KiB, stdout)."""
    t0 = time.monotonic()
    p = subprocess.run(["/usr/bin/time", "-v", *cmd], capture_output=True, text=True)
    secs = time.monotonic() - t0
    if p.returncode != 0:
        sys.exit(f"failed: {' '.join(cmd)}\n{p.stderr}")
    m = re.search(r"Maximum resident set size \(kbytes\): (\d+)", p.stderr)
    return secs, int(m.group(1)), p.stdout


def write_scene(path, glb, w, h, spp):
    """The bundled scene's two views at w × h under its two sphere lights; returns path."""
    with open(path, "w") as f:
        f.write(
            f'Scene(gltf: "{glb}", views: ["cam_front", "cam_side"], '
            f"image: (width: {w}, height: {h}), lights: ["
            "Sphere(center: (-1.8, 3.2, 1.5), radius: 0.25, radiance: (400.0, 360.0, 300.0)), "
            "Sphere(center: (2.5, 1.8, -1.5), radius: 0.2, radiance: (150.0, 170.0, 200.0))], "
            f"render: (spp: {spp}, max_bounces: 2, seed: 1))"
        )
    return path


def fit_line(xs, ys):
    """Least-squares (intercept, slope) of ys against xs."""
    n = len(xs)
    mx, my = sum(xs) / n, sum(ys) / n
    slope = sum((x - mx) * (y - my) for x, y in zip(xs, ys)) / sum((x - mx) ** 2 for x in xs)
    return my - slope * mx, slope


def slopes(a, glb, tmp):
    """The transport's time per sample against a plain render's: both timed at several spp
    (same binary, same run, alternated), each fitted by a line in spp. The slope is the cost
    per sample; the transport's intercept is what it spends per pixel whatever the samples
    (the pilot's share aside, its reduction to normal equations)."""
    w, h = (int(v) for v in a.slope_size.split("x"))
    ron = write_scene(os.path.join(tmp, f"slope{w}.ron"), glb, w, h, a.ref_spp)
    refs = os.path.join(tmp, f"slope-refs{w}")
    peak_kib([a.bin, "render-reference", ron, "--out", refs, "--quiet"])
    out = []
    for rings in (int(r) for r in a.rings.split(",")):
        spps = [int(v) for v in a.slope_spp.split(",")]
        transport, plain = [], []
        for spp in spps:
            est = os.path.join(tmp, f"slope-e{rings}-{spp}")
            _, _, stdout = peak_kib(
                [a.bin, "estimate", ron, "--reference", refs, "--out", est, "--rings",
                 str(rings), "--spp", str(spp), "--fit-only", "--quiet", "--json"]
            )
            transport.append(json.loads(stdout)["timings"]["transport_seconds"])
            _, _, rstdout = peak_kib(
                [a.bin, "render-reference", ron, "--out", os.path.join(tmp, "slope-p"),
                 "--envmap", os.path.join(est, "envmap.ron"), "--no-sphere-lights",
                 "--spp", str(spp), "--quiet", "--json"]
            )
            plain.append(json.loads(rstdout)["timings"]["render_seconds"])
        (t0, t1), (p0, p1) = fit_line(spps, transport), fit_line(spps, plain)
        row = {
            "width": w, "height": h, "views": 2, "rings": rings, "spp": spps,
            "transport_seconds": transport, "plain_render_seconds": plain,
            "transport_seconds_per_spp": t1, "plain_seconds_per_spp": p1,
            "transport_per_sample_over_plain": t1 / p1,
            "transport_intercept_seconds": t0, "plain_intercept_seconds": p0,
        }
        out.append(row)
        print(json.dumps(row), flush=True)
    return out


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--bin", default=os.path.join(ROOT, "target/release/lightprobe"))
    ap.add_argument("--out", default=os.path.join(ROOT, "docs/bench/scaling.json"))
    ap.add_argument("--sizes", default="128x96,320x240,640x480")
    ap.add_argument("--rings", default="9,25")
    ap.add_argument("--spp", type=int, default=64)
    ap.add_argument("--ref-spp", type=int, default=64)
    ap.add_argument("--slope-size", default="640x480",
                    help="image size of the per-sample measurement")
    ap.add_argument("--slope-spp", default="32,64,128,256",
                    help="transport samples of the per-sample measurement")
    a = ap.parse_args()
    glb = os.path.join(ROOT, "scenes/tabletop/tabletop.glb")
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for size in a.sizes.split(","):
            w, h = (int(v) for v in size.split("x"))
            ron = write_scene(os.path.join(tmp, f"s{w}.ron"), glb, w, h, a.ref_spp)
            for rings in (int(r) for r in a.rings.split(",")):
                out = os.path.join(tmp, f"e{w}-{rings}")
                secs, kib, stdout = peak_kib(
                    [a.bin, "estimate", ron, "--out", out, "--rings", str(rings),
                     "--spp", str(a.spp), "--quiet", "--json"]
                )
                rep = json.loads(stdout)
                t = rep["timings"]
                # The same samples as a plain render: the estimate's envmap at the transport's spp.
                plain = os.path.join(tmp, f"p{w}-{rings}")
                _, _, rstdout = peak_kib(
                    [a.bin, "render-reference", ron, "--out", plain, "--envmap",
                     os.path.join(out, "envmap.ron"), "--no-sphere-lights",
                     "--spp", str(a.spp), "--quiet", "--json"]
                )
                render_seconds = json.loads(rstdout)["timings"]["render_seconds"]
                row = {
                    "width": w, "height": h, "views": 2, "pixels": 2 * w * h,
                    "rings": rings, "cells": rep["cells"], "spp": a.spp,
                    "rel_mae": rep["rel_mae"],
                    "command_seconds": secs,
                    "transport_seconds": t["transport_seconds"],
                    "solve_seconds": t["solve_seconds"],
                    "plain_render_seconds": render_seconds,
                    "transport_over_plain_render": t["transport_seconds"] / render_seconds,
                    "transport_bytes": rep["memory"]["transport_bytes"],
                    "peak_rss_bytes": kib * 1024,
                }
                rows.append(row)
                print(json.dumps(row), flush=True)
        per_sample = slopes(a, glb, tmp)
    result = {
        "what": "estimate on the bundled scene (2 views) at several image sizes and ring counts",
        "machine_cores": os.cpu_count(),
        "rows": rows,
        "per_sample": per_sample,
    }
    os.makedirs(os.path.dirname(a.out), exist_ok=True)
    with open(a.out, "w") as f:
        json.dump(result, f, indent=1)
        f.write("\n")


if __name__ == "__main__":
    main()
