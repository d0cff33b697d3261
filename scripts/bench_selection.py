#!/usr/bin/env python3
"""What choosing costs: `estimate --rings auto`, `--model spheres` and `--model auto` against a
plain 9-ring estimate of the same scene, measured in the same run on the same binary.

The variants run in turn, round after round (--repeat), so a slow spell of a shared machine
falls on all of them; the ratio of each variant's median whole-command time to the plain
estimate's median is the figure. Each run's choice and error are recorded too, so a faster
choice that chooses worse shows. Standard library only.

    python3 scripts/bench_selection.py [--scene scenes/tabletop/tabletop.ron] [--repeat 3]
        [--bin target/release/lightprobe] [--out docs/bench/selection.json]
"""

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))

VARIANTS = {
    "rings 9": ["--rings", "9"],
    "rings auto": ["--rings", "auto"],
    "spheres:2": ["--rings", "9", "--model", "spheres:2"],
    "spheres": ["--rings", "9", "--model", "spheres"],
    "auto": ["--rings", "9", "--model", "auto"],
}


def run(bin_, scene, args, out):
    t0 = time.monotonic()
    p = subprocess.run(
        [bin_, "estimate", scene, "--out", out, "--quiet", "--json", *args],
        capture_output=True,
        text=True,
    )
    secs = time.monotonic() - t0
    if p.returncode != 0:
        sys.exit(f"failed: estimate {scene} {' '.join(args)}\n{p.stderr}")
    rep = json.loads(p.stdout)
    sel = rep.get("model_selection") or {}
    return {
        "seconds": secs,
        "model": rep["model"],
        "rings": rep["rings"],
        "rel_mae": (rep.get("spheres") or {}).get("rel_mae", rep["rel_mae"]),
        "at_noise_floor": sel.get("at_noise_floor"),
        "candidates": [c["model"] for c in sel.get("candidates", [])],
    }


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--bin", default=os.path.join(ROOT, "target/release/lightprobe"))
    ap.add_argument("--scene", default=os.path.join(ROOT, "scenes/tabletop/tabletop.ron"))
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--variants", default=",".join(VARIANTS))
    ap.add_argument("--out", default=os.path.join(ROOT, "docs/bench/selection.json"))
    a = ap.parse_args()
    names = a.variants.split(",")
    unknown = [n for n in names if n not in VARIANTS]
    if unknown or "rings 9" not in names:
        sys.exit(f"--variants: {unknown or 'must include rings 9'}; known: {list(VARIANTS)}")
    runs = {n: [] for n in names}
    with tempfile.TemporaryDirectory() as tmp:
        for r in range(a.repeat):
            for n in names:
                got = run(a.bin, a.scene, VARIANTS[n], os.path.join(tmp, f"{r}-{n}"))
                runs[n].append(got)
                print(f"round {r + 1}/{a.repeat} {n}: {got['seconds']:.1f} s, "
                      f"model {got['model']}, rings {got['rings']}, "
                      f"relMAE {100 * got['rel_mae']:.2f}%", flush=True)
    plain = statistics.median(x["seconds"] for x in runs["rings 9"])
    rows = []
    for n in names:
        med = statistics.median(x["seconds"] for x in runs[n])
        rows.append({
            "variant": n,
            "args": VARIANTS[n],
            "median_seconds": med,
            "over_plain_9_rings": med / plain,
            "runs": runs[n],
        })
        print(f"{n:>11}: median {med:6.1f} s = {med / plain:4.1f}x the plain 9-ring estimate")
    result = {
        "what": "whole-command time of estimate variants that choose, against a plain 9-ring "
                "estimate of the same scene, alternated in one run",
        "scene": os.path.relpath(a.scene, ROOT),
        "machine_cores": os.cpu_count(),
        "load_average_at_end": os.getloadavg()[0],
        "rows": rows,
    }
    os.makedirs(os.path.dirname(a.out), exist_ok=True)
    with open(a.out, "w") as f:
        json.dump(result, f, indent=1)
        f.write("\n")


if __name__ == "__main__":
    main()
