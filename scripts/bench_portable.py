#!/usr/bin/env python3
"""Speed of the portable build against a reference build, measured in the same run.

lightprobe is built for the baseline target and picks its AVX traversal kernels at run
time. This times `render-reference` (render.json timings.render_seconds: all views, no
loading or BVH build) of one scene with up to three binaries or modes, alternating them
repetition by repetition so that background load hits all alike, and reports medians,
minima (on a shared virtual machine the least disturbed run is the steadiest figure of a
deterministic workload) and their ratios:

  * NEW: the binary under test (default target/release/lightprobe), AVX kernels where the
    CPU has them;
  * NEW with LIGHTPROBE_ISA=portable: the same binary forced onto its portable kernels;
  * --reference BIN (optional): another build, e.g. one with -C target-cpu=native, built
    from the same sources or from the commit before a change.

With --reference, it also times a whole `estimate --model spheres:2` (report.json
timings.total_seconds: references, envmap fit, 325 sphere-transport renders, re-renders) of
both builds --estimate-repeat times, alternated, and checks that their `spheres/lights.ron`
are identical.

Images are checked bit-identical across all of them (the same arithmetic in the same
order); a difference fails the benchmark.

Usage: scripts/bench_portable.py [--scene S] [--spp N] [--repeat K] [--reference BIN]
       [--estimate-repeat K] [--json OUT]
"""

import argparse
import filecmp
import json
import os
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent


def render(binary, scene, spp, out, env):
    subprocess.run(
        [binary, "render-reference", str(scene), "--out", str(out), "--spp", str(spp), "--quiet"],
        check=True,
        env=env,
        stdout=subprocess.DEVNULL,
    )
    return json.loads((out / "render.json").read_text())["timings"]["render_seconds"]


def estimate(binary, scene, out, env):
    subprocess.run(
        [binary, "estimate", str(scene), "--out", str(out), "--model", "spheres:2", "--quiet"],
        check=True,
        env=env,
        stdout=subprocess.DEVNULL,
    )
    return json.loads((out / "report.json").read_text())["timings"]["total_seconds"]


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scene", default=str(ROOT / "scenes/tabletop/tabletop.ron"))
    ap.add_argument("--binary", default=str(ROOT / "target/release/lightprobe"))
    ap.add_argument("--reference", help="another lightprobe binary to compare with")
    ap.add_argument("--spp", type=int, default=512)
    ap.add_argument("--repeat", type=int, default=7)
    ap.add_argument("--estimate-repeat", type=int, default=3)
    ap.add_argument("--json")
    a = ap.parse_args()

    base_env = dict(os.environ)
    base_env.pop("LIGHTPROBE_ISA", None)
    configs = [("runtime", a.binary, base_env), ("portable", a.binary, dict(base_env, LIGHTPROBE_ISA="portable"))]
    if a.reference:
        configs.append(("reference", a.reference, base_env))
    times = {name: [] for name, _, _ in configs}
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        for r in range(a.repeat):
            for name, binary, env in configs:
                out = tmp / f"{name}-{r}"
                times[name].append(render(binary, a.scene, a.spp, out, env))
        # Same images from every build and mode.
        first = tmp / f"runtime-0"
        for name, _, _ in configs:
            for exr in sorted(first.glob("*.exr")):
                other = tmp / f"{name}-0" / exr.name
                if not filecmp.cmp(exr, other, shallow=False):
                    sys.exit(f"bench_portable: {name} renders {exr.name} differently from runtime")
        estimates = {}
        if a.reference:
            pair = [c for c in configs if c[0] != "portable"]
            estimates = {name: [] for name, _, _ in pair}
            for r in range(a.estimate_repeat):
                for name, binary, env in pair:
                    estimates[name].append(estimate(binary, a.scene, tmp / f"est-{name}-{r}", env))
            if not filecmp.cmp(
                tmp / "est-runtime-0/spheres/lights.ron", tmp / "est-reference-0/spheres/lights.ron", shallow=False
            ):
                sys.exit("bench_portable: the two builds estimate different sphere lights")
    med = {k: statistics.median(v) for k, v in times.items()}
    result = {
        "scene": os.path.relpath(a.scene, ROOT),
        "spp": a.spp,
        "repeat": a.repeat,
        "binaries": {name: os.path.relpath(b, ROOT) if b.startswith(str(ROOT)) else Path(b).name for name, b, _ in configs},
        "median_render_seconds": med,
        "all_render_seconds": times,
        "min_render_seconds": {k: min(v) for k, v in times.items()},
        "portable_over_runtime": med["portable"] / med["runtime"],
        "images_identical": True,
    }
    if a.reference:
        result["runtime_over_reference"] = med["runtime"] / med["reference"]
        result["runtime_over_reference_min"] = min(times["runtime"]) / min(times["reference"])
        est = {k: statistics.median(v) for k, v in estimates.items()}
        result["estimate_spheres2"] = {
            "repeat": a.estimate_repeat,
            "median_total_seconds": est,
            "all_total_seconds": estimates,
            "runtime_over_reference": est["runtime"] / est["reference"],
            "runtime_over_reference_min": min(estimates["runtime"]) / min(estimates["reference"]),
            "lights_identical": True,
        }
    for k, v in med.items():
        print(f"{k:>10}: {v:.3f} s median of {a.repeat}, {min(times[k]):.3f} s least")
    print(f"portable kernels / run-time AVX: {result['portable_over_runtime']:.3f}")
    if a.reference:
        print(
            f"run-time AVX / reference build: {result['runtime_over_reference']:.3f} by medians, "
            f"{result['runtime_over_reference_min']:.3f} by minima (goal <= 1.03)"
        )
        e = result["estimate_spheres2"]
        for k, v in e["median_total_seconds"].items():
            print(f"estimate --model spheres:2, {k}: {v:.2f} s median of {a.estimate_repeat}")
        print(
            f"estimate, run-time AVX / reference build: {e['runtime_over_reference']:.3f} by medians, "
            f"{e['runtime_over_reference_min']:.3f} by minima"
        )
    if a.json:
        Path(a.json).write_text(json.dumps(result, indent=2) + "\n")


if __name__ == "__main__":
    main()
