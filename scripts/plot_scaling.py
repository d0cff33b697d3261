#!/usr/bin/env python3
"""Draws docs/bench/scaling.svg from docs/bench/scaling.json (scripts/bench_scaling.py): time
and peak memory of `estimate` against the pixel count, one line per ring count. Standard
library only: a plain SVG, log-scaled pixel axis; a PNG beside it where `rsvg-convert` is
installed.

    python3 scripts/plot_scaling.py [--json docs/bench/scaling.json] [--out docs/bench/scaling.svg]
"""

import argparse
import json
import math
import os
import shutil
import subprocess

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
COLOURS = ["#3b528b", "#21918c", "#5ec962", "#fde725"]  # viridis


def nice_ticks(hi, count=5):
    """Round tick values from 0 to at least `hi`."""
    raw = hi / count
    mag = 10 ** math.floor(math.log10(raw))
    step = next(m * mag for m in (1, 2, 2.5, 5, 10) if m * mag >= raw)
    return [step * i for i in range(int(math.ceil(hi / step)) + 1)]


def panel(x0, y0, w, h, rows, key, label, unit_scale):
    """One chart: `key` of each row (scaled by unit_scale) against its pixel count."""
    out = []
    pixels = sorted({r["pixels"] for r in rows})
    lx0, lx1 = math.log10(pixels[0]) - 0.15, math.log10(pixels[-1]) + 0.15
    ticks = nice_ticks(max(r[key] * unit_scale for r in rows) * 1.05)
    ymax = ticks[-1]
    X = lambda p: x0 + (math.log10(p) - lx0) / (lx1 - lx0) * w
    Y = lambda v: y0 + h - v / ymax * h
    out.append(f'<rect x="{x0}" y="{y0}" width="{w}" height="{h}" fill="none" stroke="#444"/>')
    for t in ticks:
        out.append(f'<line x1="{x0 - 4}" y1="{Y(t):.1f}" x2="{x0 + w}" y2="{Y(t):.1f}" stroke="#ddd"/>')
        out.append(f'<text x="{x0 - 7}" y="{Y(t) + 4:.1f}" text-anchor="end">{t:g}</text>')
    for p in pixels:
        out.append(f'<line x1="{X(p):.1f}" y1="{y0 + h}" x2="{X(p):.1f}" y2="{y0 + h + 4}" stroke="#444"/>')
        out.append(f'<text x="{X(p):.1f}" y="{y0 + h + 18}" text-anchor="middle">{p / 1e6:.3g} M</text>')
    out.append(f'<text x="{x0 + w / 2}" y="{y0 + h + 38}" text-anchor="middle">pixels (2 views; log scale)</text>')
    out.append(
        f'<text x="{x0 - 48}" y="{y0 + h / 2}" text-anchor="middle" '
        f'transform="rotate(-90 {x0 - 48} {y0 + h / 2})">{label}</text>'
    )
    for i, rings in enumerate(sorted({r["rings"] for r in rows})):
        pts = sorted((r["pixels"], r[key] * unit_scale) for r in rows if r["rings"] == rings)
        c = COLOURS[i % len(COLOURS)]
        path = " ".join(f"{X(p):.1f},{Y(v):.1f}" for p, v in pts)
        out.append(f'<polyline points="{path}" fill="none" stroke="{c}" stroke-width="2"/>')
        for p, v in pts:
            out.append(f'<circle cx="{X(p):.1f}" cy="{Y(v):.1f}" r="3.5" fill="{c}"/>')
        ly = y0 + 16 + 18 * i
        out.append(f'<line x1="{x0 + 12}" y1="{ly - 4}" x2="{x0 + 32}" y2="{ly - 4}" stroke="{c}" stroke-width="2"/>')
        out.append(f'<text x="{x0 + 38}" y="{ly}">{rings} rings</text>')
    return out


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--json", default=os.path.join(ROOT, "docs/bench/scaling.json"))
    ap.add_argument("--out", default=os.path.join(ROOT, "docs/bench/scaling.svg"))
    a = ap.parse_args()
    rows = json.load(open(a.json))["rows"]
    W, H = 900, 380
    body = ['<text x="450" y="24" text-anchor="middle" font-size="15">'
            "estimate on the bundled scene, 64 spp: time and memory against image size</text>"]
    body += panel(90, 50, 320, 250, rows, "command_seconds", "whole command (s)", 1.0)
    body += panel(550, 50, 320, 250, rows, "peak_rss_bytes", "peak resident memory (MB)", 1e-6)
    svg = (
        f'<svg xmlns="http://www.w3.org/2000/svg" width="{W}" height="{H}" viewBox="0 0 {W} {H}" '
        'font-family="DejaVu Sans, Helvetica, Arial, sans-serif" font-size="12" fill="#222">\n'
        f'<rect width="{W}" height="{H}" fill="white"/>\n' + "\n".join(body) + "\n</svg>\n"
    )
    with open(a.out, "w") as f:
        f.write(svg)
    print(a.out)
    # A PNG beside it where librsvg's converter is installed (Debian: librsvg2-bin).
    if shutil.which("rsvg-convert") and a.out.endswith(".svg"):
        png = a.out[:-4] + ".png"
        subprocess.run(["rsvg-convert", a.out, "-o", png], check=True)
        print(png)


if __name__ == "__main__":
    main()
