#!/usr/bin/env python3
"""The baked-shadow study: `--fit-albedo texels` against a shadow baked into a texture.

References are rendered from the bundled scene (the true table texture); the estimates run in
`scenes/tabletop/baked_shadow/baked_shadow.ron` (the same scene, the table's texture darkened
to 40% in a soft blob; scripts/make_baked_shadow.py) with `--model spheres:2`, the white
sphere trusted: the albedo as given, `--fit-albedo materials`, and `--fit-albedo texels`; the
texels again with the references as photographs at two exposures (each view's scaled by
EXPOSURES) and `--exposure per-view`; and in the bundled scene with the true texture for the
floor. Writes `summary.json` (per run the
relMAEs, the fit test, times, each material's albedo, and the table texture's error against
the true one over all texels, inside the blob and outside) and each run's report.json and
the texels run's page figures.

    .venv/bin/python scripts/baked_shadow_study.py [--bin target/release/lightprobe] \\
        [--out docs/experiment/baked_shadow] [--texel-grid 32]
"""

import argparse
import importlib.util
import json
import shutil
import subprocess
import tempfile
from pathlib import Path

import numpy as np
from PIL import Image

ROOT = Path(__file__).resolve().parent.parent
SCENES = ROOT / "scenes" / "tabletop"


def load_maker():
    spec = importlib.util.spec_from_file_location("make_baked_shadow", ROOT / "scripts" / "make_baked_shadow.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def texture_errors(maker, fitted, multiplier):
    """Mean relative error (worst channel per texel) of fitted × multiplier against the true
    texture: over all texels, inside the blob (darkened by more than 30%) and outside."""
    true = maker.srgb_to_linear(np.asarray(maker.table_texture(), dtype=np.float64) / 255.0)
    h, w = true.shape[:2]
    uu, vv = np.meshgrid((np.arange(w) + 0.5) / w, (np.arange(h) + 0.5) / h)
    du = (uu - maker.CENTRE[0] + 0.5) % 1.0 - 0.5
    dv = (vv - maker.CENTRE[1] + 0.5) % 1.0 - 0.5
    blob = np.exp(-0.5 * ((du / maker.SIGMA[0]) ** 2 + (dv / maker.SIGMA[1]) ** 2))
    inside = blob > 0.5
    rel = np.abs(fitted * np.asarray(multiplier) / true - 1.0).max(axis=2)
    return {
        "all": float(rel.mean()),
        "inside_shadow": float(rel[inside].mean()),
        "outside_shadow": float(rel[~inside].mean()),
    }


def read_linear(path):
    return load_maker().srgb_to_linear(np.asarray(Image.open(path).convert("RGB"), dtype=np.float64) / 255.0)


# The exposures the per-view run's references are taken at, per view (cam_front, cam_side).
EXPOSURES = {"cam_front": 1.5, "cam_side": 0.6}


def scaled_references(refs, dest):
    """Each view's reference EXR times its EXPOSURES factor (alpha, the coverage, kept)."""
    import mitsuba as mi

    mi.set_variant("scalar_rgb")
    dest.mkdir()
    for view, factor in EXPOSURES.items():
        rgba = np.array(mi.Bitmap(str(refs / f"{view}.exr")), dtype=np.float32)
        rgba[..., :3] *= factor
        mi.Bitmap(rgba, mi.Bitmap.PixelFormat.RGBA).write(str(dest / f"{view}.exr"))


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--bin", default=str(ROOT / "target" / "release" / "lightprobe"))
    ap.add_argument("--out", default=str(ROOT / "docs" / "experiment" / "baked_shadow"))
    ap.add_argument("--texel-grid", type=int, default=None)
    a = ap.parse_args()
    maker = load_maker()
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    work = Path(tempfile.mkdtemp(prefix="lp-baked-"))
    refs = work / "ref"
    subprocess.run([a.bin, "render-reference", str(SCENES / "tabletop.ron"), "-o", str(refs), "--quiet"], check=True)
    baked = str(SCENES / "baked_shadow" / "baked_shadow.ron")
    trust = ["--trust-albedo", "sphere_white"]
    grid = ["--texel-grid", str(a.texel_grid)] if a.texel_grid else []
    photos = work / "photos"
    scaled_references(refs, photos)
    runs = {
        "true_texture": [str(SCENES / "tabletop.ron")],
        "as_given": [baked],
        "materials": [baked, "--fit-albedo", "materials", *trust],
        "texels": [baked, "--fit-albedo", "texels", *trust, *grid],
        "texels_per_view": [baked, "--fit-albedo", "texels", *trust, *grid, "--exposure", "per-view"],
    }
    summary = {"model": "spheres:2", "trusted": "sphere_white", "runs": {}}
    baked_texture = read_linear(SCENES / "baked_shadow" / "table_baked.png")
    for name, args in runs.items():
        dest = work / name
        subprocess.run(
            [a.bin, "estimate", *args, "--reference", str(photos if name == "texels_per_view" else refs),
             "--model", "spheres:2", "-o", str(dest), "--quiet"],
            check=True,
        )
        report = json.loads((dest / "report.json").read_text())
        shutil.copy(dest / "report.json", out / f"{name}.report.json")
        spheres = report["spheres"]
        albedo = report.get("albedo")
        row = {
            "rel_mae": spheres["rel_mae"],
            # The sphere lights against the true ones: centre error over distance, power ratio.
            "lights": [
                {
                    "centre_error_fraction_of_distance": r["centre_error_fraction_of_distance"],
                    "power_ratio": r["power_ratio"],
                }
                for r in spheres.get("recovery") or []
            ],
            "fit_test_residual_over_noise": (report.get("fit_test") or {}).get("residual_over_noise"),
            "total_seconds": report["timings"]["total_seconds"],
        }
        if report.get("exposure"):
            # Fitted against applied, both relative to their geometric mean.
            applied = np.array(list(EXPOSURES.values()))
            applied = applied / np.exp(np.log(applied).mean())
            row["exposures"] = {
                "fitted": [v["exposure"] for v in report["exposure"]["relative"]],
                "applied": applied.tolist(),
                "fits": report["exposure"]["fits"],
            }
        if name != "true_texture":
            multiplier = [1.0, 1.0, 1.0]
            texture = baked_texture
            if albedo:
                table = next(m for m in albedo["materials"] if m["name"] == "table")
                multiplier = table["multiplier"]
                row["albedo"] = {m["name"]: {"given": m["given"], "fitted": m["fitted"], "status": m["status"]} for m in albedo["materials"]}
                row["albedo_converged"] = albedo["converged"]
                row["albedo_last_change"] = albedo["last_change"]
            # The other materials were given exactly: their worst channel's error as fitted.
            if albedo:
                row["others_worst_error"] = max(
                    abs(f / g - 1.0)
                    for m in albedo["materials"]
                    if m["name"] not in ("table", "")
                    for f, g in zip(m["fitted"], m["given"])
                    if g > 0
                )
                for fit in albedo.get("texels", []):
                    # The exported texture holds texel × factor (its glTF factor is 1).
                    texture = read_linear(dest / fit["file"])
                    multiplier = [1.0, 1.0, 1.0]
                    row["texels"] = fit
                    row["texel_rounds"] = albedo["texel_rounds"]
            row["table_texture_error"] = texture_errors(maker, texture, multiplier)
        if name == "texels":
            figures = out / "figures"
            figures.mkdir(exist_ok=True)
            for f in (dest / "figures").glob("texels_*.png"):
                shutil.copy(f, figures / f.name)
        summary["runs"][name] = row
        print(name, json.dumps(row.get("table_texture_error")), "relMAE", row["rel_mae"], f"{row['total_seconds']:.1f} s")
    (out / "summary.json").write_text(json.dumps(summary, indent=1) + "\n")
    shutil.rmtree(work)


if __name__ == "__main__":
    main()
