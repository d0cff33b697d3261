#!/usr/bin/env python3
"""Coverage of the sphere model's 95% intervals over independent trials.

Each trial is a scene (the bundled one by default, or the sidecars given) with another sidecar
seed (so new references and new render noise in the fit), estimated with `--model spheres:K`,
K its number of lights. For every recovered light matched to its true light it checks whether
the truth lies inside the stated 95% interval of:

- direction (degrees, per axis: the angle between estimate and truth is inside when
  below 2.448 σ, the 95% radius of a 2-D normal),
- distance from the scene centre (± 1.96 σ, metres),
- radius (ln r within ± 1.96 σ; only where the radius is measured),
- power (luminance × radius², ln within ± 1.96 σ),
- colour (radiance / its luminance, each channel within ± 1.96 σ; three judgements a light).

Each coverage is given with its Wilson 95% interval, the binomial error of so many trials.

Writes a JSON file (docs/bench/coverage_spheres.json by default) and prints a table. Not run
in CI (about 15 s per trial of the bundled scene on 2 cores). `--extend` adds other seeds'
trials to those already in the output.

    python3 scripts/coverage_spheres.py --trials 60
    python3 scripts/coverage_spheres.py --trials 4 --out docs/bench/coverage_spheres_study.json \
        scenes/tabletop/scenarios/s{01,02,03,05,12,13,23,25,31,35,36,44,49,50,51}.ron
"""
import argparse
import json
import math
import os
import pathlib
import re
import subprocess
import tempfile

ROOT = pathlib.Path(__file__).resolve().parent.parent
SCENE = ROOT / "scenes" / "tabletop" / "tabletop.ron"


def luminance(c):
    return 0.2126 * c[0] + 0.7152 * c[1] + 0.0722 * c[2]


def sub(a, b):
    return [x - y for x, y in zip(a, b)]


def norm(a):
    return math.sqrt(sum(x * x for x in a))


def truth_lights(text):
    """The sidecar's sphere lights: (centre, radius, radiance)."""
    out = []
    # Points and colours as RON tuples or lists, as the sidecar accepts them.
    flat = re.sub(r"\s+", "", text)
    for m in re.finditer(
        r"Sphere\(center:[([]([^)\]]*)[)\]],radius:([0-9.e-]+),radiance:[([]([^)\]]*)[)\]],?\)",
        flat,
    ):
        out.append(
            (
                [float(v) for v in m.group(1).split(",")],
                float(m.group(2)),
                [float(v) for v in m.group(3).split(",")],
            )
        )
    return out


def wilson(k, n, z=1.96):
    """Wilson's 95% range of a binomial proportion: k of n judgements inside."""
    if n == 0:
        return None
    p = k / n
    mid = (p + z * z / (2 * n)) / (1 + z * z / n)
    half = z * math.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / (1 + z * z / n)
    return [mid - half, mid + half]


def scene_centre(binary, scene):
    info = json.loads(subprocess.run([binary, "info", str(scene)], check=True,
                                     capture_output=True, text=True).stdout)
    lo, hi = info["bounds"]["min"], info["bounds"]["max"]
    return [(a + b) / 2 for a, b in zip(lo, hi)]


def shown(s):
    """A scene's path as the JSON records it: relative to the repository where inside it."""
    p = pathlib.Path(s).resolve()
    return str(p.relative_to(ROOT)) if p.is_relative_to(ROOT) else str(p)


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--binary", default=str(ROOT / "target" / "release" / "lightprobe"))
    ap.add_argument("--trials", type=int, default=20)
    ap.add_argument("--first-seed", type=int, default=1)
    ap.add_argument("--out", default=str(ROOT / "docs" / "bench" / "coverage_spheres.json"))
    ap.add_argument("--extend", action="store_true",
                    help="add these trials to those already in --out (same scenes, other seeds)")
    ap.add_argument("scenes", nargs="*", default=[str(SCENE)])
    a = ap.parse_args()
    rows, skipped = [], []
    if a.extend:
        old = json.loads(pathlib.Path(a.out).read_text())
        if old["scenes"] != [shown(s) for s in a.scenes]:
            raise SystemExit(f"{a.out}: its trials are of {old['scenes']}, not these scenes")
        rows, skipped = old["lights"], old.get("not_judged", [])
        taken = {r["seed"] for r in rows}
        wanted = set(range(a.first_seed, a.first_seed + a.trials))
        if taken & wanted:
            raise SystemExit(f"{a.out}: already holds seeds {sorted(taken & wanted)}")
    with tempfile.TemporaryDirectory() as tmp:
        for scene in map(pathlib.Path, a.scenes):
            text = scene.read_text()
            truth = truth_lights(text)
            centre = scene_centre(a.binary, scene)
            gltf = re.search(r'gltf:\s*"([^"]*)"', text).group(1)
            for seed in range(a.first_seed, a.first_seed + a.trials):
                d = pathlib.Path(tmp) / f"{scene.stem}_seed{seed}"
                d.mkdir()
                if not re.search(r"seed:\s*\d+", text):
                    raise SystemExit(f"{scene}: its render settings name no seed to vary")
                sidecar = re.sub(r"seed:\s*\d+", f"seed: {seed}", text)
                sidecar = sidecar.replace(f'"{gltf}"', json.dumps(str((scene.parent / gltf).resolve())))
                (d / "scene.ron").write_text(sidecar)
                subprocess.run([a.binary, "estimate", str(d / "scene.ron"), "--out", str(d / "out"),
                                "--model", f"spheres:{len(truth)}", "--quiet"],
                               check=True, capture_output=True)
                report = json.loads((d / "out" / "report.json").read_text())
                for f in report["spheres"]["lights"]:
                    light = f["light"]
                    # A light the fit reports as lighting nothing, or as merged into a
                    # brighter one, is not a recovered light: it states no interval to judge.
                    if f["status"] in ("no_contribution", "merged"):
                        skipped.append({"scene": scene.stem, "seed": seed, "status": f["status"]})
                        continue
                    c = light["center"]
                    k = min(range(len(truth)), key=lambda j: norm(sub(truth[j][0], c)))
                    tc, tr, tl = truth[k]
                    v, tv = sub(c, centre), sub(tc, centre)
                    d_est, d_true = norm(v), norm(tv)
                    cosine = sum(x * y for x, y in zip(v, tv)) / (d_est * d_true)
                    angle = math.degrees(math.acos(max(-1.0, min(1.0, cosine))))
                    row = {
                        "scene": scene.stem,
                        "seed": seed,
                        "light": k,
                        "angle_degrees": angle,
                        "direction_sigma_degrees": f["direction_sigma_degrees"],
                        "distance_error_m": d_est - d_true,
                        "distance_sigma_m": f["distance_sigma_m"],
                        "ln_radius_error": math.log(light["radius"] / tr),
                        "radius_sigma_relative": f["radius_sigma_relative"],
                        "radius_identified": f["radius_identified"],
                        "ln_power_error": math.log(luminance(light["radiance"]) * light["radius"] ** 2
                                                   / (luminance(tl) * tr * tr)),
                        "power_sigma_relative": f["power_sigma_relative"],
                        "colour_error": sub([x / luminance(light["radiance"]) for x in light["radiance"]],
                                            [x / luminance(tl) for x in tl]),
                        "colour_sigma": f.get("colour_sigma"),
                    }
                    rows.append(row)
                print(f"{scene.stem} seed {seed}: done", flush=True)

    rows.sort(key=lambda r: (r["scene"], r["seed"], r["light"]))

    def coverage(name, inside, per_light=1, z=None):
        judged = [j for r in rows for j in (inside(r) or [None] * per_light)]
        judged = [j for j in judged if j is not None]
        n = len(judged)
        out = {"parameter": name, "judged": n, "of": per_light * len(rows),
               "covered": sum(judged), "coverage": sum(judged) / n if n else None,
               "wilson_95": wilson(sum(judged), n)}
        if z is not None:
            # Bias in units of the stated σ: 0 for an unbiased estimate, ± 1/sqrt(n) by chance.
            zs = [z(r) for r in rows if z(r) is not None]
            out["mean_z"] = sum(zs) / len(zs) if zs else None
        return out

    def z_of(r, error, sigma):
        return None if not r[sigma] else r[error] / r[sigma]

    def one(test):
        return lambda r: (lambda v: None if v is None else [v])(test(r))

    table = [
        coverage("direction", one(lambda r: None if r["direction_sigma_degrees"] is None
                 else r["angle_degrees"] < 2.448 * r["direction_sigma_degrees"])),
        coverage("distance", one(lambda r: None if r["distance_sigma_m"] is None
                 else abs(r["distance_error_m"]) < 1.96 * r["distance_sigma_m"]),
                 z=lambda r: z_of(r, "distance_error_m", "distance_sigma_m")),
        coverage("radius", one(lambda r: None if r["radius_sigma_relative"] is None
                 else abs(r["ln_radius_error"]) < 1.96 * r["radius_sigma_relative"]),
                 z=lambda r: z_of(r, "ln_radius_error", "radius_sigma_relative")),
        coverage("power", one(lambda r: None if r["power_sigma_relative"] is None
                 else abs(r["ln_power_error"]) < 1.96 * r["power_sigma_relative"]),
                 z=lambda r: z_of(r, "ln_power_error", "power_sigma_relative")),
        coverage("colour", lambda r: None if r["colour_sigma"] is None
                 else [abs(e) < 1.96 * s for e, s in zip(r["colour_error"], r["colour_sigma"])],
                 per_light=3),
    ]
    unidentified = sum(1 for r in rows if r["radius_identified"] is False)
    seeds = sorted({r["seed"] for r in rows})
    out = {"scenes": [shown(s) for s in a.scenes],
           "model": "spheres:K, K the scene's light count", "trials_per_scene": len(seeds),
           "seeds": seeds,
           "coverage": table, "radius_not_identified": unidentified, "lights": rows,
           "not_judged": skipped}
    pathlib.Path(a.out).write_text(json.dumps(out, indent=1) + "\n")
    print("| parameter | judged | truth inside its 95% interval | binomial 95% range | mean error / σ |")
    print("| --- | ---: | ---: | ---: | ---: |")
    for t in table:
        cov = "–" if t["coverage"] is None else f"{100 * t['coverage']:.0f}%"
        rng = "–" if t["wilson_95"] is None else "{:.0f}–{:.0f}%".format(*[100 * v for v in t["wilson_95"]])
        bias = "" if t.get("mean_z") is None else f"{t['mean_z']:+.2f}"
        print(f"| {t['parameter']} | {t['judged']} of {t['of']} | {cov} | {rng} | {bias} |")
    print(f"radius reported as not identified: {unidentified} of {len(rows)} lights")
    if skipped:
        print(f"not judged (no contribution, or merged into a brighter light): {len(skipped)} lights")


if __name__ == "__main__":
    main()
