#!/usr/bin/env python3
"""Speed of the portable build against a reference build, measured in the same run.

lightprobe is built for the baseline target and picks its AVX traversal kernels at run
time. This times `render-reference` (render.json timings.render_seconds: all views, no
loading or BVH build) of one scene with up to three binaries or modes, alternating them
repetition by repetition so that background load hits all alike, and reports medians and
ratios:

  * NEW: the binary under test (default target/release/lightprobe), AVX kernels where the
    CPU has them;
  * NEW with LIGHTPROBE_ISA=portable: the same binary forced onto its portable kernels;
  * --reference BIN (optional): another build, e.g. one with -C target-cpu=native, built
    from the same sources or from the commit before a change.

Images are checked bit-identical across all of them (the same arithmetic in the same
order); a difference fails the benchmark.

Usage: scripts/bench_portable.py [--scene S] [--spp N] [--repeat K] [--reference BIN]
       [--json OUT]
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


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scene", default=str(ROOT / "scenes/tabletop/tabletop.ron"))
    ap.add_argument("--binary", default=str(ROOT / "target/release/lightprobe"))
    ap.add_argument("--reference", help="another lightprobe binary to compare with")
    ap.add_argument("--spp", type=int, default=512)
    ap.add_argument("--repeat", type=int, default=7)
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
    med = {k: statistics.median(v) for k, v in times.items()}
    result = {
        "scene": os.path.relpath(a.scene, ROOT),
        "spp": a.spp,
        "repeat": a.repeat,
        "binaries": {name: os.path.relpath(b, ROOT) if b.startswith(str(ROOT)) else Path(b).name for name, b, _ in configs},
        "median_render_seconds": med,
        "all_render_seconds": times,
        "portable_over_runtime": med["portable"] / med["runtime"],
        "images_identical": True,
    }
    if a.reference:
        result["runtime_over_reference"] = med["runtime"] / med["reference"]
    for k, v in med.items():
        print(f"{k:>10}: {v:.3f} s median of {a.repeat}")
    print(f"portable kernels / run-time AVX: {result['portable_over_runtime']:.3f}")
    if a.reference:
        print(f"run-time AVX / reference build: {result['runtime_over_reference']:.3f} (goal <= 1.03)")
    if a.json:
        Path(a.json).write_text(json.dumps(result, indent=2) + "\n")


if __name__ == "__main__":
    main()
