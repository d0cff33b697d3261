#!/usr/bin/env python3
"""Helper of scripts/check_exr_oiio.sh: check every EXR of a lightprobe render folder with
OpenImageIO's command-line tools (iinfo, oiiotool) as an external oracle.

For each *.exr in RENDER_DIR:
  * `iinfo -v` must read it; size must be the view's camera size (scene_truth.py's
    reading of the scene, checked against `lightprobe info`);
    channels must be float R,G,B,A (beauty, `<view>.exr`) or float R,G,B (AOV,
    `<view>.<aov>.exr`, as listed in render.json views[].aov).
  * `oiiotool --printstats` channel averages of R,G,B must match lightprobe's mean within
    1e-5 relative + 1e-7 absolute: render.json views[].mean_rgb for beauty images, the mean
    computed with Mitsuba's EXR reader (as in check_trimesh.py) for AOVs.
    --printstats prints averages with 6 decimals (rounding up to 5e-7, coarser than the
    tolerance for small means), so the comparison uses `oiiotool FILE --mulc 2^20
    --printstats`: scaling float32 pixels by a power of two is exact, so OIIO's average
    of the scaled image is exactly 2^20 x its average of the file, printed with ~5e-13
    resolution. The plain --printstats averages are shown too and must agree with the
    scaled ones to within their print rounding.
  * Cross-checks (also required): Mitsuba's mean of R,G,B vs OIIO's; for beauty images
    the A channel average vs render.json views[].coverage.

Usage: check_exr_oiio.py RENDER_DIR [--lightprobe BIN] [--scene SCENE.ron]
Exit status: 0 = pass, 1 = failure.
"""

from __future__ import annotations

import argparse
import json
import re
import shutil
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from lpcheck_common import (DEFAULT_LIGHTPROBE, REPO, CheckError, find_lightprobe,  # noqa: E402
                            log, read_exr, run)
import scene_truth  # noqa: E402

REL_TOL = 1e-5
ABS_TOL = 1e-7
SCALE = 2.0 ** 20
PRINT_RES = 5e-7 * (1 + 1e-6)      # half of the last printed decimal of --printstats


def parse_iinfo(text: str, path: Path) -> dict:
    m = re.search(r":\s*(\d+)\s*x\s*(\d+),\s*(\d+)\s+channel,\s*(\S+)\s+(\S+)", text)
    if not m:
        raise ValueError(f"unrecognised iinfo output: {text.strip()[:200]!r}")
    out = {"width": int(m.group(1)), "height": int(m.group(2)), "nchannels": int(m.group(3)),
           "format": m.group(4), "file_format": m.group(5)}
    cm = re.search(r"channel list:\s*(.+)", text)
    out["channels"] = [c.strip() for c in cm.group(1).split(",")] if cm else []
    return out


def parse_printstats(text: str) -> list[np.ndarray]:
    """Every 'Stats Avg:' line of oiiotool --printstats output, in order."""
    avgs = []
    for line in text.splitlines():
        m = re.match(r"\s*Stats Avg:\s*(.*?)\s*(\((\w+)\))?\s*$", line)
        if m:
            avgs.append(np.array([float(x) for x in m.group(1).split()], dtype=np.float64))
    return avgs


def resolve_scene(arg: Path | None, render_json: dict, render_dir: Path) -> Path:
    if arg is not None:
        cands = [arg]
    else:
        s = render_json.get("scene")
        if not s:
            raise CheckError("render.json has no `scene`; pass --scene (or SCENE=...)")
        p = Path(s)
        cands = [p] if p.is_absolute() else [Path.cwd() / p, REPO / p, render_dir / p]
    for c in cands:
        if c.is_file():
            return c.resolve()
    raise CheckError("scene sidecar not found; tried " + ", ".join(map(str, cands)))


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("render_dir", type=Path)
    ap.add_argument("--lightprobe", type=Path, default=DEFAULT_LIGHTPROBE)
    ap.add_argument("--scene", type=Path, default=None,
                    help="scene sidecar (default: render.json's `scene`)")
    args = ap.parse_args()
    try:
        sys.stdout.reconfigure(line_buffering=True)
    except AttributeError:
        pass
    t_start = time.monotonic()
    try:
        return check(args, t_start)
    except CheckError as e:
        log(f"ERROR: {e}")
        log("RESULT: FAIL (check could not run)")
        return 1


def check(args, t_start: float) -> int:
    for tool in ("iinfo", "oiiotool"):
        if shutil.which(tool) is None:
            raise CheckError(f"`{tool}` not on PATH (Debian/Ubuntu: apt-get install "
                             f"openimageio-tools)")
    rdir = args.render_dir.resolve()
    rj_path = rdir / "render.json"
    if not rj_path.is_file():
        raise CheckError(f"{rj_path} not found (not a lightprobe render-reference folder?)")
    rj = json.loads(rj_path.read_text())
    scene = resolve_scene(args.scene, rj, rdir)
    binary = find_lightprobe(args.lightprobe.resolve())
    try:
        desc = scene_truth.described(scene, binary, log=log)
    except scene_truth.TruthError as e:
        raise CheckError(str(e)) from e
    cams = {c["name"]: c for c in desc["cameras"]}
    ver = run(["oiiotool", "--version"], "oiiotool --version").stdout.strip()
    log(f"render dir: {rdir}")
    log(f"scene:      {scene}")
    log(f"oiiotool:   {shutil.which('oiiotool')} (OpenImageIO {ver})")

    # what each EXR is supposed to be, from render.json (matched by file name in rdir)
    expected: dict[str, dict] = {}
    for v in rj.get("views", []):
        view = v["view"]
        expected[Path(v["exr"]).name] = {"view": view, "kind": "beauty",
                                         "mean": v.get("mean_rgb"), "coverage": v.get("coverage")}
        for aov, p in (v.get("aov") or {}).items():
            expected[Path(p).name] = {"view": view, "kind": aov}

    problems: list[str] = []
    if rj.get("image"):
        for name, cam in cams.items():
            if (cam["width"], cam["height"]) != (rj["image"]["width"], rj["image"]["height"]):
                problems.append(f"render.json image {rj['image']} differs from camera {name} "
                                f"size {cam['width']}x{cam['height']}")
    files = sorted(rdir.glob("*.exr"))
    if not files:
        raise CheckError(f"no *.exr files in {rdir}")
    for missing in sorted(set(expected) - {f.name for f in files}):
        problems.append(f"{missing}: listed in render.json but missing from {rdir}")

    rows = []
    for f in files:
        exp = expected.get(f.name)
        if exp is None:
            problems.append(f"{f.name}: not listed in render.json (stale file?) - cannot check")
            continue
        if exp["view"] not in cams:
            problems.append(f"{f.name}: view {exp['view']!r} is not a camera of the scene")
            continue
        cam = cams[exp["view"]]
        want_ch = ["R", "G", "B", "A"] if exp["kind"] == "beauty" else ["R", "G", "B"]
        fp = f"{f.name}:"

        # iinfo -v
        proc = run(["iinfo", "-v", f], f"iinfo -v {f.name}")
        if re.search(r"\bERROR\b", proc.stdout + proc.stderr):
            problems.append(f"{fp} iinfo reported an error: {(proc.stdout + proc.stderr).strip()}")
        try:
            ii = parse_iinfo(proc.stdout, f)
        except ValueError as e:
            problems.append(f"{fp} {e}")
            continue
        fmt_ok = (ii["width"], ii["height"]) == (cam["width"], cam["height"])
        if not fmt_ok:
            problems.append(f"{fp} iinfo size {ii['width']}x{ii['height']}, camera "
                            f"{exp['view']} is {cam['width']}x{cam['height']}")
        if ii["file_format"] != "openexr":
            fmt_ok = False
            problems.append(f"{fp} iinfo file format {ii['file_format']}, expected openexr")
        if ii["format"] != "float" or ii["channels"] != want_ch or ii["nchannels"] != len(want_ch):
            fmt_ok = False
            problems.append(f"{fp} iinfo: {ii['nchannels']} channel {ii['format']} "
                            f"{ii['channels']}, expected float {want_ch}")

        # oiiotool --printstats (plain, and on the exactly 2^20-scaled image)
        plain = parse_printstats(run(["oiiotool", f, "--printstats"],
                                     f"oiiotool --printstats {f.name}").stdout)
        scaled = parse_printstats(run(["oiiotool", f, "--mulc", f"{SCALE:.0f}", "--printstats"],
                                      f"oiiotool --mulc --printstats {f.name}").stdout)
        if len(plain) != 1 or len(scaled) != 1 or len(plain[0]) < 3 or len(scaled[0]) < 3:
            problems.append(f"{fp} could not parse oiiotool --printstats averages")
            continue
        oiio_plain, oiio = plain[0], scaled[0] / SCALE
        if np.any(np.abs(oiio_plain - oiio) > PRINT_RES):
            problems.append(f"{fp} oiiotool plain averages {oiio_plain.tolist()} inconsistent "
                            f"with scaled ones {oiio.tolist()}")

        # lightprobe's mean and the Mitsuba-read mean
        arr, names, _fmt = read_exr(f)
        mi_mean = arr.astype(np.float64).reshape(-1, arr.shape[-1]).mean(axis=0)
        if exp["kind"] == "beauty":
            if exp.get("mean") is None:
                problems.append(f"{fp} render.json has no mean_rgb")
                continue
            lp_mean = np.asarray(exp["mean"], dtype=np.float64)
            lp_src = "render.json"
        else:
            lp_mean = mi_mean[:3]
            lp_src = "mitsuba"
        tol = REL_TOL * np.abs(lp_mean) + ABS_TOL
        d_lp = np.abs(oiio[:3] - lp_mean)
        mean_ok = bool(np.all(d_lp <= tol))
        d_mi = np.abs(oiio[:3] - mi_mean[:3])
        mi_ok = bool(np.all(d_mi <= REL_TOL * np.abs(mi_mean[:3]) + ABS_TOL))
        if not mean_ok:
            problems.append(f"{fp} OIIO mean RGB {oiio[:3].tolist()} vs {lp_src} "
                            f"{lp_mean.tolist()}: |diff| {d_lp.tolist()} > tol {tol.tolist()}")
        if not mi_ok:
            problems.append(f"{fp} OIIO mean RGB {oiio[:3].tolist()} vs Mitsuba-read mean "
                            f"{mi_mean[:3].tolist()}")
        cov_msg = ""
        if exp["kind"] == "beauty" and exp.get("coverage") is not None and len(oiio) >= 4:
            dc = abs(oiio[3] - float(exp["coverage"]))
            cov_ok = dc <= REL_TOL * abs(float(exp["coverage"])) + ABS_TOL
            cov_msg = (oiio[3], oiio_plain[3], float(exp["coverage"]), dc,
                       dc / max(abs(float(exp["coverage"])), 1e-30))
            if not cov_ok:
                mean_ok = False
                problems.append(f"{fp} OIIO alpha average {oiio[3]!r} vs render.json "
                                f"coverage {exp['coverage']!r}")
        rows.append(dict(file=f.name, kind=exp["kind"], size=f"{ii['width']}x{ii['height']}",
                         ch=",".join(ii["channels"]) + f" {ii['format']}", fmt_ok=fmt_ok,
                         oiio=oiio[:3], plain=oiio_plain[:3], lp=lp_mean, src=lp_src,
                         rel=(d_lp / np.maximum(np.abs(lp_mean), 1e-30)),
                         absd=d_lp, ok=fmt_ok and mean_ok and mi_ok, cov=cov_msg))

    # ---- table
    fw = max([4] + [len(r["file"]) for r in rows])
    log(f"{'file':<{fw}s}  {'kind':<6s} {'size':>7s} {'channels':<15s} {'ch':>2s} "
        f"{'oiiotool avg (2^20-scaled)':>26s} {'--printstats':>12s} {'lightprobe mean':>18s} "
        f"{'source':<11s} {'|diff|':>9s} {'rel diff':>9s}  result")
    for r in rows:
        for c in range(3):
            first = c == 0
            log(f"{(r['file'] if first else ''):<{fw}s}  {(r['kind'] if first else ''):<6s} "
                f"{(r['size'] if first else ''):>7s} {(r['ch'] if first else ''):<15s} "
                f"{'RGB'[c]:>2s} {r['oiio'][c]:>26.12f} {r['plain'][c]:>12.6f} "
                f"{r['lp'][c]:>18.12f} {(r['src'] if first else ''):<11s} "
                f"{r['absd'][c]:>9.2e} {r['rel'][c]:>9.2e}  "
                f"{('PASS' if r['ok'] else 'FAIL') if first else ''}")
        if r["cov"]:
            a, ap, cov, d, rel = r["cov"]
            log(f"{'':<{fw}s}  {'':<6s} {'':>7s} {'':<15s} {'A':>2s} {a:>26.12f} {ap:>12.6f} "
                f"{cov:>18.12f} {'coverage':<11s} {d:>9.2e} {rel:>9.2e}")
    log(f"criteria: iinfo size = camera size, float channels R,G,B,A (beauty) / R,G,B (AOV); "
        f"|oiio avg - mean| <= {REL_TOL:g}*|mean| + {ABS_TOL:g} per channel")
    for p in problems:
        log(f"FAIL: {p}")
    ok = not problems and rows and all(r["ok"] for r in rows)
    log(f"RESULT: {'PASS' if ok else 'FAIL'}  ({len(rows)} EXR files, "
        f"{time.monotonic() - t_start:.1f} s)")
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
