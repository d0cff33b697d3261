#!/usr/bin/env python3
"""Closed-form check of direct lighting from one sphere light (no Mitsuba
needed for the truth; Mitsuba is rendered alongside as a second opinion).

Scene (written to a temp dir): a 4 x 4 m Lambertian plane (albedo 0.5, no
NORMAL) at y = 0, a camera 2 m above it looking straight down (yfov 1.0,
64x64), one sphere light of radius r and radiance L at height h. A single
plane has no interreflection, so every bounce count gives direct light only,
and the exact outgoing radiance at a plane point x is

    L_o(x) = albedo * L * (r / d)^2 * cos(theta)

(d = |c - x|, theta = angle between the plane normal and c - x; exact while
the whole sphere is above the plane's horizon: the irradiance of a sphere of
radiance L is pi * L * sin^2(alpha) * cos(theta), sin(alpha) = r / d).
Pixels are box-filtered with 8x8 supersampling; pixels whose camera ray
hits the (hidden, occluding) light sphere are left out.

For each light placement it prints the ratio of each renderer's mean to the
closed form (whole image, and the 4x4 pixels right under the light):
lightprobe --strategy mis / light-only / bsdf-only, and Mitsuba's path
integrator. PASS iff lightprobe's default (mis) is within 1 % of the closed
form on the whole image and under the light, for every placement. The
1 % tolerance is far above the Monte Carlo error of light sampling here
(Mitsuba's light-sampled estimate lands within 0.1 %); bsdf-only is printed
for information (it is much noisier with small lights).

Usage: .venv/bin/python scripts/check_sphere_light.py [--spp 256] [--workdir DIR]
"""

from __future__ import annotations

import argparse
import math
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import mitsuba_scene as ms  # noqa: E402

ALBEDO, W, H, YFOV, CAM_H = 0.5, 64, 64, 1.0, 2.0
# (centre, radius, radiance): near light, farther ones, one like the tabletop's key light
PLACEMENTS = [
    ((0.6, 1.0, 0.0), 0.1, 100.0),
    ((0.6, 2.0, 0.0), 0.1, 100.0),
    ((0.6, 3.0, 0.0), 0.1, 100.0),
    ((-1.8, 3.2, 1.5), 0.25, 400.0),
]
TOL = 0.01


def write_plane(dirpath: Path) -> Path:
    import make_tabletop as mt
    g = mt.GltfBuilder()
    pos = np.array([[-2, 0, 2], [2, 0, 2], [2, 0, -2], [-2, 0, -2]], float)
    mat = g.material("grey", (ALBEDO,) * 3)
    roots = [g.node("plane", mesh=g.mesh("plane", dict(positions=pos, indices=np.array(
        [[0, 1, 2], [0, 2, 3]])), mat))]
    eye = np.array([0.0, CAM_H, 0.0])
    rot = mt.look_at_rotation(eye, (0, 0, 0), up=(0, 0, -1))
    g.gltf["cameras"].append({"name": "top", "type": "perspective", "perspective": {
        "yfov": YFOV, "aspectRatio": W / H, "znear": 0.01}})
    roots.append(g.node("top", camera=0, translation=eye, rotation=mt.mat_to_quat(rot)))
    glb = dirpath / "plane.glb"
    glb.write_bytes(g.glb(roots))
    return glb


def closed_form(cam: dict, c, r, L, n=8):
    t = math.tan(cam["yfov"] / 2)
    o, f = np.array(cam["origin"]), np.array(cam["forward"])
    right, up = np.array(cam["right"]), np.array(cam["up"])
    sub = (np.arange(n) + 0.5) / n
    ix = (np.arange(W)[:, None] + sub[None, :]).ravel()
    iy = (np.arange(H)[:, None] + sub[None, :]).ravel()
    X, Y = np.meshgrid((2 * ix / W - 1) * t * W / H, (1 - 2 * iy / H) * t)
    d = f + X[..., None] * right + Y[..., None] * up
    d /= np.linalg.norm(d, axis=-1, keepdims=True)
    s = -o[1] / d[..., 1]
    p = o + s[..., None] * d
    v = np.asarray(c) - p
    dist = np.linalg.norm(v, axis=-1)
    lo = ALBEDO * L * (r / dist) ** 2 * (v[..., 1] / dist)
    lo = np.where((np.abs(p[..., 0]) <= 2) & (np.abs(p[..., 2]) <= 2), lo, 0.0)
    # camera rays that hit the light sphere before the plane
    oc = o - np.asarray(c)
    b = (d * oc).sum(-1)
    disc = b * b - (oc * oc).sum() + r * r
    tl = -b - np.sqrt(np.maximum(disc, 0))
    blocked = (disc > 0) & (tl > 0) & (tl < s)
    bad = blocked.reshape(H, n, W, n).any(axis=(1, 3))
    return lo.reshape(H, n, W, n).mean(axis=(1, 3)), ~bad


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--bin", type=Path, default=ms.DEFAULT_BIN)
    ap.add_argument("--spp", type=int, default=256)
    ap.add_argument("--workdir", type=Path, default=None)
    args = ap.parse_args()
    work = args.workdir or Path(tempfile.mkdtemp(prefix="check_sphere_light_"))
    work.mkdir(parents=True, exist_ok=True)
    ms.set_variant()
    import mitsuba as mi
    write_plane(work)
    print(f"workdir {work}; plane albedo {ALBEDO}, camera {CAM_H} m above, {W}x{H}, "
          f"{args.spp} spp; ratios = renderer mean / closed form")
    ok = True
    for k, (c, r, L) in enumerate(PLACEMENTS):
        ron = work / f"light{k}.ron"
        ron.write_text(f'Scene(gltf: "plane.glb", views: ["top"], image: (width: {W}, height: {H}),'
                       f' lights: [Sphere(center: ({c[0]}, {c[1]}, {c[2]}), radius: {r},'
                       f' radiance: ({L}, {L}, {L}))], render: (spp: {args.spp},'
                       f' max_bounces: 1, seed: 1))\n')
        desc = ms.described_scene(ron, args.bin)
        truth, keep = closed_form(desc["cameras"][0], c, r, L)
        imgs = {}
        for st in ("mis", "light-only", "bsdf-only"):
            out = work / f"light{k}_{st}"
            ms.run_lightprobe([str(args.bin), "render-reference", str(ron), "--out", str(out),
                               "--strategy", st, "--quiet"])
            imgs[f"lightprobe {st}"] = np.array(mi.Bitmap(str(out / "top.exr")))[..., 0]
        S = ms.build_scene(ron, args.bin, desc=desc)
        imgs["Mitsuba path"] = S.render("top", seed=0)[..., 0]
        # 4x4 pixels under the light (if it is inside the image)
        cam = desc["cameras"][0]
        tx = math.tan(cam["yfov"] / 2) * W / H
        col = int(round(W / 2 + c[0] / CAM_H / tx * W / 2))
        row = int(round(H / 2 + c[2] / CAM_H / math.tan(cam["yfov"] / 2) * H / 2))
        under = (slice(max(row - 2, 0), row + 2), slice(max(col - 2, 0), col + 2))
        has_under = 2 <= col < W - 2 and 2 <= row < H - 2 and keep[under].all()
        print(f"\nlight centre {c}, radius {r}, radiance {L}: closed-form mean "
              f"{truth[keep].mean():.5f}" + (f", under the light (px {row},{col}) "
                                             f"{truth[under].mean():.4f}" if has_under else ""))
        for name, img in imgs.items():
            tot = img[keep].mean() / truth[keep].mean()
            und = img[under].mean() / truth[under].mean() if has_under else float("nan")
            rmae = np.abs(img[keep] - truth[keep]).sum() / truth[keep].sum()
            flag = ""
            if name == "lightprobe mis":
                bad = abs(tot - 1) >= TOL or (has_under and abs(und - 1) >= TOL)
                flag = "  <- FAIL" if bad else "  ok"
                ok &= not bad
            print(f"  {name:22s} mean ratio {tot:.4f}  under-light ratio {und:.4f}  "
                  f"relMAE vs closed form {rmae:.4f}{flag}")
    print(f"\n{'PASS' if ok else 'FAIL'}: lightprobe (mis) direct light from a sphere "
          f"{'matches' if ok else 'does not match'} the closed form within {TOL:.0%}")
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
