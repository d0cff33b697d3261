#!/usr/bin/env python3
"""External check: lightprobe's USD export, opened with Pixar's USD (usd-core).

`lightprobe estimate` writes OUT/lights.usda (a DomeLight of the envmap) and,
with --model spheres..., OUT/spheres/lights.usda (a SphereLight per light).
This script runs an estimate of the bundled scene (64x48, --model spheres:2)
and reads both stages through the USD library, not as text:

 1. stage metadata: upAxis Y, metersPerUnit 1 (glTF's frame), default prim;
 2. every SphereLight's radius, color x intensity x 2^exposure (its radiance,
    normalize off) and world-space position equal the fitted lights of
    spheres/lights.ron and of report.json (f32 precision); a radius report.json
    calls not identified carries lightprobe:radiusIdentified = false and its
    95% interval (lightprobe:radius95, where it is within a factor 100), an
    identified one neither;
 3. the DomeLight: texture format latlong, intensity 1, its texture file
    resolves; and the texture's orientation is OpenEXR's lat-long convention,
    which UsdLux adopts for a +Y-up stage. This is checked independently of
    lightprobe's code: for every pixel, the direction the OpenEXR spec gives it
    (column j at longitude pi - 2 pi j/(W-1), longitude 0 = +Z, pi/2 = +X; row i
    at latitude pi/2 - pi i/(H-1), +pi/2 = +Y) is looked up in envmap.ron with
    scripts/ring_grid.py; the pixel must hold that cell's radiance. At least
    99.9 % of pixels must (a pixel centre on a cell edge may round either way).
Self-test: the texture mirrored in longitude, turned a quarter about +Y, or
upside down must each fail step 3. (Mitsuba's convention, that of envmap.exr,
differs from OpenEXR's by half a pixel in azimuth, the poles alike: 99.99 % of
its pixels would pass, so either file orients a DomeLight right.)

Usage: .venv/bin/python scripts/check_usd.py [--workdir DIR]
"""

from __future__ import annotations

import argparse
import json
import math
import re
import sys
import tempfile
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
MATCH_MIN = 0.999


def log(msg: str = "") -> None:
    print(msg, flush=True)


def dome_matches(exr: np.ndarray, grid, radiance: np.ndarray) -> float:
    """Fraction of pixels holding the radiance of the cell OpenEXR's convention puts them in."""
    h, w = exr.shape[:2]
    j, i = np.meshgrid(np.arange(w), np.arange(h))
    lon = math.pi - 2 * math.pi * j / (w - 1)
    lat = math.pi / 2 - math.pi * i / (h - 1)
    d = np.stack([np.cos(lat) * np.sin(lon), np.sin(lat), np.cos(lat) * np.cos(lon)], -1)
    want = radiance[grid.cell_of_dirs(d)]
    return float(np.mean(np.all(exr[..., :3] == want.astype(np.float32), axis=-1)))


def main() -> int:
    sys.path.insert(0, str(HERE))
    import lpcheck_common as lc
    import ring_grid as rg
    from pxr import Sdf, Usd, UsdGeom, UsdLux

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--bin", type=Path, default=lc.DEFAULT_LIGHTPROBE, help="lightprobe binary")
    ap.add_argument("--scene", type=Path, default=lc.DEFAULT_SCENE)
    ap.add_argument("--workdir", type=Path, default=None)
    args = ap.parse_args()
    work = (args.workdir or Path(tempfile.mkdtemp(prefix="check_usd_"))).resolve()
    work.mkdir(parents=True, exist_ok=True)
    binary = lc.find_lightprobe(args.bin)
    out = work / "estimate"
    lc.run([binary, "estimate", args.scene, "--height", 48, "--model", "spheres:2", "--spp", 64,
            "--out", out, "--quiet"], "lightprobe estimate --model spheres:2")
    log(f"usd-core {Usd.GetVersion()}; outputs in {out}")
    ok = True

    # ---- 1, 2: the sphere lights
    stage = Usd.Stage.Open(str(out / "spheres" / "lights.usda"))
    meta_ok = (UsdGeom.GetStageUpAxis(stage) == UsdGeom.Tokens.y
               and UsdGeom.GetStageMetersPerUnit(stage) == 1.0
               and stage.GetDefaultPrim().GetPath() == Sdf.Path("/Lights"))
    log(f"[1] spheres/lights.usda: upAxis {UsdGeom.GetStageUpAxis(stage)}, metersPerUnit "
        f"{UsdGeom.GetStageMetersPerUnit(stage)}, default prim "
        f"{stage.GetDefaultPrim().GetPath()} -> {'PASS' if meta_ok else 'FAIL'}")
    ok &= meta_ok
    text = (out / "spheres" / "lights.ron").read_text()
    ron = [[float(x) for x in re.findall(r"-?[\d.]+(?:e-?\d+)?", line)]
           for line in text.splitlines() if line.strip().startswith("Sphere(")]
    report = json.loads((out / "report.json").read_text())
    usd = []
    for prim in stage.Traverse():
        if prim.IsA(UsdLux.SphereLight):
            li = UsdLux.SphereLight(prim)
            gain = li.GetIntensityAttr().Get() * 2.0 ** li.GetExposureAttr().Get()
            pos = UsdGeom.Xformable(prim).ComputeLocalToWorldTransform(
                Usd.TimeCode.Default()).ExtractTranslation()
            ident = prim.GetAttribute("lightprobe:radiusIdentified")
            interval = prim.GetAttribute("lightprobe:radius95")
            usd.append({"name": prim.GetName(), "radius": li.GetRadiusAttr().Get(),
                        "identified": ident.Get() if ident.IsValid() else None,
                        "radius95": list(interval.Get()) if interval.IsValid() else None,
                        "radiance": np.array(li.GetColorAttr().Get()) * gain,
                        "center": np.array(pos), "normalize": li.GetNormalizeAttr().Get()})
    lights_ok = len(usd) == len(ron) == 2
    for u, r in zip(usd, ron):
        c, rad, L = np.array(r[:3]), r[3], np.array(r[4:7])
        good = (not u["normalize"] and np.allclose(u["center"], c, rtol=1e-6, atol=1e-6)
                and math.isclose(u["radius"], rad, rel_tol=1e-6)
                and np.allclose(u["radiance"], L, rtol=1e-6))
        lights_ok &= good
        log(f"[2] {u['name']}: centre {np.round(u['center'], 5).tolist()} radius "
            f"{u['radius']:.6g} radiance {np.round(u['radiance'], 4).tolist()} vs lights.ron "
            f"{np.round(c, 5).tolist()} {rad:.6g} {np.round(L, 4).tolist()} -> "
            f"{'same' if good else 'DIFFERENT'}")
    # report.json's fitted lights are the same
    fitted = [li["light"] for li in (report.get("spheres") or {}).get("lights", [])]
    same = len(fitted) == len(usd) and all(
        np.allclose(f["center"], u["center"], rtol=1e-6, atol=1e-6)
        and math.isclose(f["radius"], u["radius"], rel_tol=1e-6)
        and np.allclose(f["radiance"], u["radiance"], rtol=1e-6) for f, u in zip(fitted, usd))
    log(f"[2] report.json's spheres.lights: {len(fitted)} lights -> "
        f"{'same' if same else 'DIFFERENT'}")
    lights_ok &= same
    # A radius the images do not identify says so through USD: a custom attribute, with the
    # 95% interval ×/÷ exp(1.96 σ) where report.json measures one; identified ones carry none.
    kept = [f for f in (report.get("spheres") or {}).get("lights", [])
            if f.get("status") in ("identified", "distance_unidentified")]
    for f, u in zip(kept, usd):
        sigma = f.get("radius_sigma_relative")
        if f.get("radius_identified") is False:
            # The interval is written where it says something: a factor of at most 100.
            factor = math.exp(1.96 * sigma) if sigma is not None and 1.96 * sigma < 700 else math.inf
            r = f["light"]["radius"]
            want = [r / factor, r * factor] if factor <= 100 else None
            good = u["identified"] is False and (
                u["radius95"] is None if want is None
                else u["radius95"] is not None and np.allclose(u["radius95"], want, rtol=1e-5))
        else:
            good = u["identified"] is None and u["radius95"] is None
        log(f"[2] {u['name']}: report radius_identified {f.get('radius_identified')}, USD "
            f"lightprobe:radiusIdentified {u['identified']}, radius95 {u['radius95']} -> "
            f"{'same' if good else 'DIFFERENT'}")
        lights_ok &= good
    ok &= lights_ok

    # ---- 3: the dome
    stage = Usd.Stage.Open(str(out / "lights.usda"))
    domes = [UsdLux.DomeLight(p) for p in stage.Traverse() if p.IsA(UsdLux.DomeLight)]
    dome_ok = len(domes) == 1
    if dome_ok:
        d = domes[0]
        tex = d.GetTextureFileAttr().Get()
        path = Path(tex.resolvedPath) if tex.resolvedPath else None
        dome_ok = (d.GetTextureFormatAttr().Get() == "latlong" and d.GetIntensityAttr().Get() == 1
                   and path is not None and path.is_file())
        log(f"[3] DomeLight: texture {tex.path} resolves to {path}, format "
            f"{d.GetTextureFormatAttr().Get()}, intensity {d.GetIntensityAttr().Get()} -> "
            f"{'PASS' if dome_ok else 'FAIL'}")
        rings, radiance = rg.read_envmap_ron(out / "envmap.ron")
        grid = rg.RingGrid(rings)
        if dome_ok:
            frac = dome_matches(lc.read_exr(path)[0], grid, radiance)
            good = frac >= MATCH_MIN
            log(f"[3] {path.name}: {frac:.4%} of pixels hold the radiance of the cell OpenEXR's "
                f"lat-long convention puts them in (>= {MATCH_MIN:.1%}) -> "
                f"{'PASS' if good else 'FAIL'}")
            dome_ok &= good
            exr = lc.read_exr(path)[0]
            w = exr.shape[1]
            for what, bad in (("mirrored in longitude", exr[:, ::-1]),
                              ("turned a quarter about +Y", np.roll(exr, w // 4, axis=1)),
                              ("upside down", exr[::-1])):
                wrong = dome_matches(bad, grid, radiance)
                caught = wrong < MATCH_MIN
                log(f"[self-test] the texture {what}: {wrong:.2%} of pixels match -> "
                    f"{'FAIL, as it must' if caught else 'PASSED: the check cannot tell'}")
                dome_ok &= caught
    ok &= dome_ok
    log(f"\nCHECK {'PASS' if ok else 'FAIL'}: lightprobe's USD export read by USD {Usd.GetVersion()}")
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
