#!/usr/bin/env python3
"""Speed benchmark: lightprobe vs Mitsuba 3 (llvm_ad_rgb) on the same scene.

Renders every view of the sidecar (default: scenes/tabletop/bench_views.ron,
the bundled tabletop at 128x96, 512 spp, max_bounces 2, with a third view,
cam_table, that sees geometry in every pixel) with
  * lightprobe `render-reference` (a new process per repetition): its own
    render time, render.json timings.render_seconds (all views; excludes
    loading and BVH build), and the wall time of the whole process;
  * Mitsuba 3 llvm_ad_rgb, same meshes, cameras, spp and depth (scene from
    scripts/mitsuba_scene.py; path integrator with MIS, no Russian
    roulette). The scene is built once; each view is rendered once untimed
    for JIT warm-up ("first", reported, includes tracing/compiling the
    kernel, which Dr.Jit caches in ~/.drjit), then timed per repetition.
In the same run (unless --no-envmap), the same scene lit by a 21-ring
envmap instead of its sphere lights (written by scripts/ring_grid.py: a dim
sky, 0.05-0.15, plus three bright cells; `render-reference --envmap ENV
--no-sphere-lights`), to show what envmap sampling costs lightprobe:
samples/s under the envmap, under the sphere lights, and their ratio
(envmap / sphere; the goal is close to 1). Mitsuba is also timed under the
same envmap exported with `lightprobe export-envmap --width 1024` (its
`envmap` emitter; the width barely matters for speed).
Repetitions alternate lightprobe and Mitsuba (and sphere and envmap runs) so
that background load hits all alike; medians are reported.
samples/s = W * H * spp * views / seconds. It counts samples of "blind" pixels
too (pixels whose rays can meet no geometry: the same black image whoever
renders them), which lightprobe skips: so samples/s is also given per view,
beside the view's blind-pixel fraction (render.json coverage), and cam_table
has none. Speed at equal noise (below) is the fair headline.
Prints a summary and writes one JSON object (to --json OUT if given).

--equal-noise runs a different benchmark instead (the samples/s one above is
then skipped): speed at equal noise. Samples/s alone is unfair to lightprobe,
whose stratified first bounce (padded Sobol) has ~7x less variance per sample
than Mitsuba's `independent` sampler, so here Mitsuba gets each of its
samplers (--samplers; default independent, stratified, multijitter, ldsampler,
orthogonal) and the best one counts. In one run, interleaved as above:
  * every view is rendered at each spp of --spp-list (default 64 to 2048)
    with seeds 1..K (K = --seeds, default 4) by lightprobe and by Mitsuba with
    each sampler. Mitsuba rounds some counts (ldsampler to a power of 4,
    orthogonal to a prime squared, stratified to a square, multijitter to a
    product of near-equal factors): the spp it really used is recorded and
    used, a count it already measured is skipped, a sampler it rejects is
    skipped; all are reported;
  * noise = the relative MSE of one render: per-pixel variance across the K
    seeds (unbiased; for K = 2 that is (a - b)^2 / 2) summed over RGB and
    the pixels of every view inside lightprobe's geometry mask (alpha > 0 at
    the largest spp), divided by the sum of the squared per-pixel mean. Same
    metric for both tools. (relMAE between seeds 1 and 2 is also reported.)
  * time = the render time of all views, median over the K seeds
    (lightprobe: render.json timings.render_seconds; Mitsuba: after one
    untimed warm-up render per view and configuration, as above);
  * per configuration, log-log fit noise = C * spp^-a and linear fit
    time = t0 + k * spp; for the noise target (default: lightprobe's measured
    noise at --target-spp, default 512 or the largest spp listed) the spp
    needed, spp* = (C / target)^(1/a), and the time t0 + k * spp*
    ("extrapolated" when spp* lies outside the spp measured); as a
    cross-check, also the time from piecewise log-log interpolation of the
    measured (time, noise) points, which follows curves that bend (Mitsuba's
    stratified and ldsampler gain less than a power law at high spp here);
  * Mitsuba time / lightprobe time per sampler, and the headline: the best
    (fastest) sampler's ratio, "equal-noise speed ratio (>1 = lightprobe
    faster)", among the samplers whose spp* lies inside their measured spp or
    at most MAX_EXTRAPOLATION (1.2x) beyond (no headline when none does);
  * the same image: both tools' time at the target spp (Mitsuba's
    `independent` sampler), and how much noisier Mitsuba's image is.
Writes a chart of noise vs render time (log-log; points measured, lines
fitted, dashed where extrapolated) to --out (default out/bench) as
equal_noise.png; the figures go under "equal_noise" in the JSON.

Usage: .venv/bin/python scripts/bench.py [--repeat 3] [--json OUT] [--scene S.ron]
       [--spp N] [--threads N] [--no-envmap] [--envmap-rings 21]
       .venv/bin/python scripts/bench.py --equal-noise [--spp-list 64,128,256,512]
       [--samplers independent,stratified,...] [--target-spp 512] [--out out/bench]
       [--seeds 4] [--json OUT] [--scene S.ron] [--threads N]
"""

from __future__ import annotations

import argparse
import json
import math
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import check_mitsuba as cm  # noqa: E402
import mitsuba_scene as ms  # noqa: E402
from figure_check import assert_text_apart  # noqa: E402
import ring_grid as rg  # noqa: E402


def bench_envmap(rings: int) -> tuple:
    """Dim sky plus three bright cells (sun-like warm, blue, white) at
    different heights; cells of a 21-ring grid are ~9 deg across, hence the
    higher radiance than a 9-ring map would need."""
    g = rg.RingGrid(rings)
    pick = lambda frac_ring, frac_phi: (round(frac_ring * (rings - 1)),  # noqa: E731
                                        int(frac_phi * g.counts[round(frac_ring * (rings - 1))]))
    bright = [(*pick(0.25, 0.70), (60.0, 50.0, 40.0)),      # theta ~45 deg
              (*pick(0.40, 0.20), (15.0, 25.0, 50.0)),      # theta ~72 deg
              (*pick(0.15, 0.45), (20.0, 20.0, 20.0))]      # theta ~27 deg
    return rg.demo_envmap(rings, bright), bright


def run_lightprobe(bin_: Path, scene: Path, out: Path, spp: int, threads: int | None,
                   extra: list | None = None) -> dict:
    cmd = [str(bin_)]
    if threads:
        cmd += ["--threads", str(threads)]
    cmd += ["render-reference", str(scene), "--out", str(out), "--spp", str(spp),
            "--quiet", "--json"] + [str(x) for x in (extra or [])]
    for _ in range(20):                 # the binary may vanish briefly during a rebuild
        if bin_.exists():
            break
        time.sleep(3)
    t0 = time.perf_counter()
    r = subprocess.run(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    wall = time.perf_counter() - t0
    if r.returncode != 0:
        raise RuntimeError(f"{' '.join(cmd)} failed ({r.returncode}):\n{r.stderr}")
    rj = json.loads(r.stdout)
    return {"wall": wall, "render": rj["timings"]["render_seconds"], "json": rj}


# --------------------------------------------------------------------------
# --equal-noise
# --------------------------------------------------------------------------

def write_result(result: dict, path: Path | None) -> None:
    """The run's JSON object: to `path` if given, else to stdout."""
    text = json.dumps(result, indent=2)
    if path:
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(text + "\n")
        print(f"wrote {path}")
    else:
        print(text)


MITSUBA_SAMPLERS = ("independent", "stratified", "multijitter", "ldsampler", "orthogonal")
# The equal-noise headline uses only times read inside the measured spp, or at most this
# factor beyond them.
MAX_EXTRAPOLATION = 1.2
BENCH_SCENE = ms.REPO / "scenes" / "tabletop" / "bench_views.ron"


def int_list(text: str) -> list[int]:
    return sorted({int(x) for x in text.split(",") if x.strip()})


def noise_of(renders: list[dict], masks: dict) -> dict:
    """renders: one {view: (H, W, 3) RGB} per seed. Relative MSE of one render
    (per-pixel unbiased variance across seeds / squared mean, summed over RGB,
    masked pixels and views) and relMAE between the first two seeds."""
    var_sum = mean_sq = mae_num = mae_den = 0.0
    for v, mask in masks.items():
        x = np.stack([r[v][mask] for r in renders]).astype(np.float64)   # (K, N, 3)
        var_sum += x.var(axis=0, ddof=1).sum()
        mean_sq += (x.mean(axis=0) ** 2).sum()
        mae_num += np.abs(x[1] - x[0]).sum()
        mae_den += np.abs(x[0]).sum()
    return {"rel_mse": float(var_sum / mean_sq), "rel_mae_pair": float(mae_num / mae_den)}


def fit_config(spp: list, noise: list, secs: list) -> dict | None:
    """noise = C * spp^-a (least squares in log-log) and time = t0 + k * spp
    (least squares; t0 >= 0, else a line through the origin, since a negative
    overhead is only noise). None with fewer than two spp."""
    if len(spp) < 2:
        return None
    s, n, t = (np.asarray(x, dtype=np.float64) for x in (spp, noise, secs))
    slope, icpt = np.polyfit(np.log(s), np.log(n), 1)
    k, t0 = np.polyfit(s, t, 1)
    if t0 < 0:
        k, t0 = float((s * t).sum() / (s * s).sum()), 0.0
    # how well a power law describes the noise (some samplers' curves bend)
    resid = np.log(n) - (icpt + slope * np.log(s))
    return {"a": float(-slope), "C": float(np.exp(icpt)), "t0": float(t0), "k": float(k),
            "noise_rms_log_residual": float(np.sqrt((resid ** 2).mean()))}


def local_target_seconds(noise: list, secs: list, target: float) -> float:
    """Cross-check of the fits: time at the target by piecewise-linear
    interpolation of log time vs log noise between the measured points (the
    two nearest points' line beyond them). It follows a bending curve that a
    single power law averages out."""
    order = np.argsort(noise)
    ln, lt = np.log(np.asarray(noise)[order]), np.log(np.asarray(secs)[order])
    i = int(np.clip(np.searchsorted(ln, np.log(target)), 1, len(ln) - 1))
    f = (np.log(target) - ln[i - 1]) / (ln[i] - ln[i - 1])
    return float(np.exp(lt[i - 1] + f * (lt[i] - lt[i - 1])))


def at_target(fit: dict, target: float, spp: list) -> dict:
    """spp and time a configuration needs for the target noise, along its fits.
    extrapolation: how far spp* lies outside the measured spp, as a factor
    (1 = inside). Up to 5% beyond counts as inside: the fits' own error is of
    that order (lightprobe's fit puts its own target spp a few % off)."""
    need = (fit["C"] / target) ** (1.0 / fit["a"])
    factor = max(min(spp) / need, need / max(spp), 1.0)
    return {"spp": need, "seconds": fit["t0"] + fit["k"] * need,
            "extrapolated": bool(factor > 1.05), "extrapolation_factor": factor}


def equal_noise_chart(path: Path, configs: dict, target: float, target_label: str) -> None:
    """Noise vs render time, log-log: measured points, fitted curves (solid over
    the measured spp, dashed out to the target), target line and crossings."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    fig, ax = plt.subplots(figsize=(8, 5.5))
    cmap = plt.get_cmap("viridis")
    others = [n for n in configs if n != "lightprobe"]
    for name, c in configs.items():
        if not c["spp"]:
            continue
        # lightprobe in black; Mitsuba's samplers along viridis, its yellow end left out.
        col = "black" if name == "lightprobe" else \
            cmap(0.85 * others.index(name) / max(1, len(others) - 1))
        ax.plot(c["seconds"], c["rel_mse"], "o", color=col, label=name)
        f, t = c.get("fit"), c.get("target")
        if not f:
            continue
        lo, hi = min(c["spp"]), max(c["spp"])
        s = np.geomspace(lo, hi, 50)
        ax.plot(f["t0"] + f["k"] * s, f["C"] * s ** -f["a"], "-", color=col, lw=1)
        if t["extrapolated"]:
            s = np.geomspace(min(lo, t["spp"]), max(hi, t["spp"]), 50)
            ax.plot(f["t0"] + f["k"] * s, f["C"] * s ** -f["a"], "--", color=col, lw=1)
        ax.plot([t["seconds"]], [target], "x", color=col, ms=9)
    ax.axhline(target, color="grey", lw=0.8, ls=":", label=f"target ({target_label})")
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel("render time, all views (s)")
    ax.set_ylabel("relative MSE of one render")
    ax.set_title("Equal noise: lightprobe vs Mitsuba 3 samplers (x = time at the target)")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    assert_text_apart(fig, path.name)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=120)
    fig.savefig(path.with_suffix(".svg"))
    plt.close(fig)


def run_equal_noise(args, variant: str) -> int:
    import drjit as dr
    import mitsuba as mi
    # Mitsuba warns on every rounded sample count; we report those ourselves
    mi.set_log_level(mi.LogLevel.Error)
    desc = ms.described_scene(args.scene, args.bin)
    st = desc["settings"]
    cams = {c["name"]: c for c in desc["cameras"]}
    views = list(cams)
    w, h = st["width"], st["height"]
    spp_list = int_list(args.spp_list)
    samplers = [x.strip() for x in args.samplers.split(",") if x.strip()]
    n_seeds = max(2, args.seeds)           # two renders at least: noise needs a pair
    seeds = list(range(1, n_seeds + 1))
    target_spp = args.target_spp or (512 if 512 in spp_list else max(spp_list))
    if target_spp not in spp_list:
        print(f"--target-spp {target_spp} is not in --spp-list {spp_list}", file=sys.stderr)
        return 2
    print(f"equal-noise benchmark: scene {args.scene}, views {views}, {w}x{h}, max_bounces "
          f"{st['max_bounces']}; spp {spp_list}; seeds {seeds}; {os.cpu_count()} CPUs, load "
          f"average {os.getloadavg()[0]:.2f}")
    load_before = os.getloadavg()

    meshes = ms.load_meshes(ms.sidecar_gltf(args.scene))
    S = ms.build_scene(args.scene, args.bin, desc=desc, meshes=meshes)
    # Mitsuba sensors per (sampler, requested spp); keep the spp it really uses
    sensors, notes = {}, []
    for smp in samplers:
        seen = {}
        for n in spp_list:
            try:
                sens = {v: mi.load_dict(ms.sensor_dict(cams[v], n, sampler=smp)) for v in views}
            except Exception as e:  # noqa: BLE001 - Mitsuba raises RuntimeError subclasses
                notes.append(f"Mitsuba {smp}: rejected at {n} spp ({str(e).splitlines()[0]}); "
                             "skipped")
                continue
            actual = sens[views[0]].sampler().sample_count()
            if actual in seen:
                notes.append(f"Mitsuba {smp}: {n} spp -> {actual}, already measured "
                             f"(from {seen[actual]}); skipped")
                continue
            if actual != n:
                notes.append(f"Mitsuba {smp}: {n} spp rounded to {actual}")
            seen[actual] = n
            sensors[(smp, n)] = (actual, sens)
    for line in notes:
        print("  " + line)

    def mi_render(sensor, seed):
        img = mi.render(S.scene, sensor=sensor, seed=seed)
        return np.array(img, dtype=np.float32)[..., :3]   # np.array forces evaluation

    lp_img = {n: [] for n in spp_list}            # spp -> per seed {view: RGB}
    lp_sec = {n: [] for n in spp_list}
    lp_alpha = {}
    mi_img = {key: [] for key in sensors}
    mi_sec = {key: [] for key in sensors}
    mi_first = {}
    t_start = time.perf_counter()
    with tempfile.TemporaryDirectory(prefix="bench_noise_") as tmp:
        # seeds outermost and tools alternating inside, so that background load
        # hits every configuration alike
        for seed in seeds:
            for n in spp_list:
                out = Path(tmp) / f"lp_{n}_{seed}"
                res = run_lightprobe(args.bin, args.scene, out, n, args.threads,
                                     ["--seed", seed])
                lp_sec[n].append(res["render"])
                lp_threads = res["json"].get("threads")
                imgs = {v: cm.read_exr(out / f"{v}.exr") for v in views}
                lp_img[n].append({v: a[..., :3] for v, a in imgs.items()})
                if n == max(spp_list) and seed == seeds[0]:
                    lp_alpha = {v: a[..., 3] for v, a in imgs.items()}
                shutil.rmtree(out)
                for key, (actual, sens) in list(sensors.items()):
                    if key[1] != n:
                        continue
                    try:
                        if key not in mi_first:        # JIT warm-up, untimed
                            t0 = time.perf_counter()
                            for v in views:
                                mi_render(sens[v], 0)
                            mi_first[key] = time.perf_counter() - t0
                        t0 = time.perf_counter()
                        imgs = {v: mi_render(sens[v], seed) for v in views}
                        mi_sec[key].append(time.perf_counter() - t0)
                    except Exception as e:  # noqa: BLE001
                        line = (f"Mitsuba {key[0]}: render failed at {actual} spp "
                                f"({str(e).splitlines()[0]}); skipped")
                        print("  " + line)
                        notes.append(line)
                        del sensors[key], mi_img[key], mi_sec[key]
                        continue
                    mi_img[key].append(imgs)
            print(f"  seed {seed}/{n_seeds} done ({time.perf_counter() - t_start:.0f} s)",
                  flush=True)
    load_after = os.getloadavg()

    masks = {v: a > 0 for v, a in lp_alpha.items()}
    n_px = sum(int(m.sum()) for m in masks.values())
    med = statistics.median
    configs = {"lightprobe": {"spp": spp_list, "requested_spp": spp_list}}
    configs.update({f"Mitsuba {smp}": {"spp": [], "requested_spp": []} for smp in samplers})
    lp = configs["lightprobe"]
    for n in spp_list:
        nz = noise_of(lp_img[n], masks)
        lp.setdefault("rel_mse", []).append(nz["rel_mse"])
        lp.setdefault("rel_mae_pair", []).append(nz["rel_mae_pair"])
        lp.setdefault("seconds", []).append(med(lp_sec[n]))
        lp.setdefault("seconds_all", []).append(lp_sec[n])
    for (smp, n), (actual, _) in sensors.items():
        c = configs[f"Mitsuba {smp}"]
        nz = noise_of(mi_img[(smp, n)], masks)
        c["spp"].append(actual)
        c["requested_spp"].append(n)
        c.setdefault("rel_mse", []).append(nz["rel_mse"])
        c.setdefault("rel_mae_pair", []).append(nz["rel_mae_pair"])
        c.setdefault("seconds", []).append(med(mi_sec[(smp, n)]))
        c.setdefault("seconds_all", []).append(mi_sec[(smp, n)])
        c.setdefault("first_render_seconds", []).append(mi_first[(smp, n)])
    # the target: lightprobe's measured noise at target_spp
    target = lp["rel_mse"][spp_list.index(target_spp)]
    for name, c in configs.items():
        if not c["spp"]:
            continue
        c["samples_per_second"] = [w * h * len(views) * n / t
                                   for n, t in zip(c["spp"], c["seconds"])]
        c["fit"] = fit_config(c["spp"], c["rel_mse"], c["seconds"])
        if c["fit"]:
            c["target"] = at_target(c["fit"], target, c["spp"])
            c["target"]["seconds_local"] = local_target_seconds(c["rel_mse"], c["seconds"],
                                                                target)
    lp_t = lp["target"]["seconds"]
    ratios, ratios_local = {}, {}
    for name, c in configs.items():
        if name != "lightprobe" and c.get("target"):
            c["target"]["ratio_mitsuba_over_lightprobe"] = c["target"]["seconds"] / lp_t
            ratios[name] = c["target"]["seconds"] / lp_t
            ratios_local[name] = c["target"]["seconds_local"] / lp["target"]["seconds_local"]
            c["target"]["ratio_local"] = ratios_local[name]
    # the headline: Mitsuba's fastest sampler among those whose time at the target was
    # measured, not extrapolated more than MAX_EXTRAPOLATION beyond their spp
    inside = {n: r for n, r in ratios.items()
              if configs[n]["target"]["extrapolation_factor"] <= MAX_EXTRAPOLATION}
    lp_inside = lp["target"]["extrapolation_factor"] <= MAX_EXTRAPOLATION
    best = min(inside, key=inside.get) if inside and lp_inside else None
    fastest_any = min(ratios, key=ratios.get) if ratios else None
    # the same image: both tools at the target spp (Mitsuba's independent sampler, the only
    # one that takes any spp as asked)
    same = configs.get("Mitsuba independent", {})
    same_image = None
    if target_spp in same.get("spp", []):
        t_mi = same["seconds"][same["spp"].index(target_spp)]
        t_lp = lp["seconds"][spp_list.index(target_spp)]
        same_image = {"spp": target_spp, "lightprobe_seconds": t_lp, "mitsuba_seconds": t_mi,
                      "ratio_mitsuba_over_lightprobe": t_mi / t_lp,
                      "noise_ratio_mitsuba_over_lightprobe":
                          same["rel_mse"][same["spp"].index(target_spp)]
                          / lp["rel_mse"][spp_list.index(target_spp)],
                      # every sampler at the spp it measured nearest the target
                      "noise_ratio_per_sampler": {
                          n: c["rel_mse"][k] / lp["rel_mse"][spp_list.index(target_spp)]
                          for n, c in configs.items() if n != "lightprobe" and c["spp"]
                          for k in [int(np.argmin([abs(x - target_spp) for x in c["spp"]]))]},
                      "noise_ratio_per_sampler_spp": {
                          n: c["spp"][int(np.argmin([abs(x - target_spp) for x in c["spp"]]))]
                          for n, c in configs.items() if n != "lightprobe" and c["spp"]}}
    result = {
        "scene": str(args.scene), "triangles": desc["triangles"], "width": w, "height": h,
        "views": views, "max_bounces": st["max_bounces"], "cpus": os.cpu_count(),
        "loadavg_before": load_before, "loadavg_after": load_after,
        "equal_noise": {
            "metric": "relative MSE of one render: per-pixel variance across seeds "
                      "(ddof 1) / squared per-pixel mean, summed over RGB and the masked "
                      "pixels of all views (mask: lightprobe alpha > 0)",
            "seeds": seeds, "spp_list": spp_list, "masked_pixels": {
                v: int(m.sum()) for v, m in masks.items()},
            "mitsuba": {"version": mi.__version__, "variant": variant,
                        "threads": dr.thread_count(),
                        "integrator": "path (MIS), max_depth = max_bounces + 1, no Russian "
                                      "roulette"},
            "lightprobe_threads": lp_threads,
            "notes": notes,
            "target": {"rel_mse": target, "from": f"lightprobe measured at {target_spp} spp"},
            "configs": configs,
            "ratio_mitsuba_over_lightprobe": ratios,
            # the same from piecewise interpolation of the measured points
            "ratio_mitsuba_over_lightprobe_local": ratios_local,
            "max_extrapolation": MAX_EXTRAPOLATION,
            "best_mitsuba_sampler": best,
            # the headline: Mitsuba's best sampler (measured, not extrapolated) vs lightprobe
            # at equal noise; None when no sampler's time at the target was measured
            "equal_noise_speed_ratio": ratios.get(best) if best else None,
            "fastest_sampler_including_extrapolated": fastest_any,
            "same_image": same_image,
            "wall_seconds": time.perf_counter() - t_start,
        },
    }

    print(f"\nnoise = relative MSE of one render over {n_px} masked pixels ({n_seeds} seeds); "
          f"time = median render time of all views (s)")
    print(f"  {'configuration':22s} {'spp':>5s} {'rel MSE':>10s} {'relMAE':>8s} {'time':>7s} "
          f"{'M smp/s':>8s}")
    for name, c in configs.items():
        for i, n in enumerate(c["spp"]):
            req = "" if c["requested_spp"][i] == n else f" (asked {c['requested_spp'][i]})"
            print(f"  {name if i == 0 else '':22s} {n:5d} {c['rel_mse'][i]:10.3e} "
                  f"{c['rel_mae_pair'][i] * 100:7.2f}% {c['seconds'][i]:7.3f} "
                  f"{c['samples_per_second'][i] / 1e6:8.2f}{req}")
    print(f"\nfits (noise = C spp^-a, rms error of that fit; time = t0 + k spp) and the time "
          f"to reach the target noise {target:.3e} (lightprobe at {target_spp} spp); (local) = "
          f"ratio from piecewise log-log interpolation of the measured points instead:")
    print(f"  {'configuration':22s} {'a':>5s} {'fit err':>7s} {'t0 s':>6s} {'ms/spp':>7s} "
          f"{'spp needed':>11s} {'time s':>8s} {'Mitsuba/lp':>10s} {'(local)':>8s}")
    for name, c in configs.items():
        if not c.get("fit"):
            if name != "lightprobe":
                print(f"  {name:22s} (not fitted: fewer than two spp measured)")
            continue
        f, t = c["fit"], c["target"]
        ratio = (f"{t['ratio_mitsuba_over_lightprobe']:10.2f} {t['ratio_local']:8.2f}"
                 if name in ratios else " " * 19)
        err = math.expm1(f["noise_rms_log_residual"]) * 100
        print(f"  {name:22s} {f['a']:5.2f} {err:6.1f}% {f['t0']:6.3f} {f['k'] * 1e3:7.3f} "
              f"{t['spp']:11.0f} {t['seconds']:8.3f} {ratio}"
              + (f"  extrapolated (x{t['extrapolation_factor']:.2f} beyond the measured spp)"
                 if t["extrapolated"] else ""))
    if best:
        print(f"\nequal-noise speed ratio (>1 = lightprobe faster): {ratios[best]:.2f} "
              f"(Mitsuba's best sampler measured at the target: {best.split(' ', 1)[1]}; by "
              f"local interpolation {ratios_local[best]:.2f}; with `independent`: "
              f"{ratios.get('Mitsuba independent', float('nan')):.2f})")
    else:
        print(f"\nno equal-noise headline: no configuration reached the target within "
              f"{MAX_EXTRAPOLATION}x of its measured spp (extend --spp-list)")
    if fastest_any and fastest_any != best:
        print(f"  ({fastest_any} would be faster at {ratios[fastest_any]:.2f}, but its time "
              f"is extrapolated x{configs[fastest_any]['target']['extrapolation_factor']:.2f} "
              f"beyond its measured spp: not used)")
    if same_image:
        print(f"the same image ({target_spp} spp, Mitsuba `independent`): Mitsuba "
              f"{same_image['mitsuba_seconds']:.2f} s / lightprobe "
              f"{same_image['lightprobe_seconds']:.2f} s = "
              f"{same_image['ratio_mitsuba_over_lightprobe']:.2f}x; its noise is "
              f"{same_image['noise_ratio_mitsuba_over_lightprobe']:.2f}x lightprobe's; "
              "near that spp, every sampler's noise over lightprobe's: "
              + ", ".join(f"{n.split(' ', 1)[1]} {r:.2f}x "
                          f"({same_image['noise_ratio_per_sampler_spp'][n]} spp)"
                          for n, r in same_image["noise_ratio_per_sampler"].items()))
    if load_before[0] > 0.5:
        print(f"  note: 1-min load average was {load_before[0]:.2f} on {os.cpu_count()} CPUs "
              f"before the run: other work may have slowed both tools")
    chart = args.out / "equal_noise.png"
    equal_noise_chart(chart, configs, target, f"lightprobe at {target_spp} spp")
    result["equal_noise"]["chart"] = str(chart)
    print(f"wrote {chart}")
    write_result(result, args.json)
    return 0


# --------------------------------------------------------------------------
# samples/s (default)
# --------------------------------------------------------------------------

def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scene", type=Path, default=BENCH_SCENE,
                    help="default: the bundled scene with a third view that sees geometry in "
                         "every pixel (scenes/tabletop/bench_views.ron)")
    ap.add_argument("--bin", type=Path, default=ms.DEFAULT_BIN, help="lightprobe binary")
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--spp", type=int, default=None, help="default: the sidecar's")
    ap.add_argument("--threads", type=int, default=None,
                    help="threads for both (default: all cores, each tool's default)")
    ap.add_argument("--json", type=Path, default=None, help="write the result JSON here")
    ap.add_argument("--no-envmap", dest="envmap", action="store_false",
                    help="skip the envmap-lit runs")
    ap.add_argument("--envmap-rings", type=int, default=21)
    ap.add_argument("--equal-noise", action="store_true",
                    help="run the equal-noise benchmark instead (see the docstring)")
    ap.add_argument("--spp-list", default="64,128,256,512,1024,2048",
                    help="--equal-noise: spp to measure (comma-separated); they must span the "
                         "spp each tool needs for the target noise (a time more than "
                         f"{MAX_EXTRAPOLATION}x beyond them is not used for the headline)")
    ap.add_argument("--seeds", type=int, default=4,
                    help="--equal-noise: renders per configuration (noise from their spread)")
    ap.add_argument("--samplers", default=",".join(MITSUBA_SAMPLERS),
                    help="--equal-noise: Mitsuba sampler types (comma-separated)")
    ap.add_argument("--target-spp", type=int, default=None,
                    help="--equal-noise: target = lightprobe's noise at this spp (one of "
                         "--spp-list; default 512 if listed, else the largest)")
    ap.add_argument("--replot", type=Path, default=None,
                    help="only redraw the equal-noise chart from a result JSON's "
                         "equal_noise section (into --out)")
    ap.add_argument("--out", type=Path, default=ms.REPO / "out" / "bench",
                    help="--equal-noise: directory of the chart")
    args = ap.parse_args()
    if args.replot:
        eq = json.loads(args.replot.read_text())["equal_noise"]
        chart = args.out / "equal_noise.png"
        equal_noise_chart(chart, eq["configs"], eq["target"]["rel_mse"], eq["target"]["from"])
        print(f"redrew {chart} (and .svg) from {args.replot}")
        return 0

    if not ms.install_llvm19():
        print("bench.py needs Mitsuba's llvm_ad_rgb variant (libLLVM 19)", file=sys.stderr)
        return 2
    variant = ms.set_variant(require_llvm=True)
    import drjit as dr
    import mitsuba as mi
    if args.threads:
        dr.set_thread_count(args.threads)
    if args.equal_noise:
        return run_equal_noise(args, variant)

    desc = ms.described_scene(args.scene, args.bin)
    st = desc["settings"]
    spp = args.spp or st["spp"]
    views = [c["name"] for c in desc["cameras"]]
    w, h = st["width"], st["height"]
    samples = w * h * spp * len(views)
    print(f"scene {args.scene}: {desc['triangles']} triangles, views {views}, {w}x{h}, "
          f"{spp} spp, max_bounces {st['max_bounces']} -> {samples:,} samples per run; "
          f"{os.cpu_count()} CPUs, load average {os.getloadavg()[0]:.2f}")
    load_before = os.getloadavg()

    # Mitsuba: build once, warm up (JIT) once per view
    meshes = ms.load_meshes(ms.sidecar_gltf(args.scene))
    t0 = time.perf_counter()
    S = ms.build_scene(args.scene, args.bin, spp=spp, desc=desc, meshes=meshes)
    build_s = time.perf_counter() - t0
    first = {}
    for v in views:
        t0 = time.perf_counter()
        S.render(v, seed=0)               # np.array() inside forces evaluation
        first[v] = time.perf_counter() - t0
    first_total = sum(first.values())
    print(f"Mitsuba {mi.__version__} {variant} ({dr.thread_count()} threads): scene build "
          f"{build_s:.2f} s, first render (incl. JIT) {first_total:.2f} s "
          + ", ".join(f"{v} {s:.2f} s" for v, s in first.items()))

    lp_render, lp_wall, mi_render, lp_threads, lp_views = [], [], [], None, []
    mi_views, coverage = [], {}
    env_lp_render, env_lp_wall, env_lp_views, env_mi_render = [], [], [], []
    env_info = None
    with tempfile.TemporaryDirectory(prefix="bench_") as tmp:
        if args.envmap:
            rad, bright = bench_envmap(args.envmap_rings)
            env_ron = Path(tmp) / f"envmap_{args.envmap_rings}.ron"
            rg.write_envmap_ron(env_ron, args.envmap_rings, rad)
            env_exr = Path(tmp) / "envmap.exr"
            ms.run_lightprobe([str(args.bin), "export-envmap", str(env_ron), "--out",
                               str(env_exr), "--width", "1024"])
            g = rg.RingGrid(args.envmap_rings)
            t0 = time.perf_counter()
            S_env = ms.build_scene(args.scene, args.bin, spp=spp, desc=desc, meshes=meshes,
                                   envmap=env_exr, sphere_lights=False)
            env_build_s = time.perf_counter() - t0
            env_first = 0.0
            for v in views:
                t0 = time.perf_counter()
                S_env.render(v, seed=0)
                env_first += time.perf_counter() - t0
            env_info = {"rings": args.envmap_rings, "cells": g.n_cells,
                        "bright_cells": [{"ring": r, "index": j, "cell": g.cell(r, j),
                                          "radiance": list(c)} for r, j, c in bright],
                        "sky_radiance_range": [float(rad.min()),
                                               float(np.sort(rad.max(1))[-len(bright) - 1])],
                        "mitsuba_export_width": 1024}
            print(f"envmap: {args.envmap_rings} rings, {g.n_cells} cells, bright cells "
                  + ", ".join(f"ring {r} #{j} {c}" for r, j, c in bright)
                  + f"; Mitsuba envmap scene build {env_build_s:.2f} s, first render "
                  f"{env_first:.2f} s")
        for r in range(args.repeat):
            res = run_lightprobe(args.bin, args.scene, Path(tmp) / f"lp{r}", spp, args.threads)
            lp_render.append(res["render"])
            lp_wall.append(res["wall"])
            lp_threads = res["json"].get("threads")
            lp_views.append({v["view"]: v["seconds"] for v in res["json"]["views"]})
            coverage = {v["view"]: v["coverage"] for v in res["json"]["views"]}
            mi_views.append({})
            for v in views:
                t0 = time.perf_counter()
                S.render(v, seed=r + 1)
                mi_views[-1][v] = time.perf_counter() - t0
            mi_render.append(sum(mi_views[-1].values()))
            line = (f"  rep {r + 1}/{args.repeat}: lightprobe render {res['render']:.2f} s "
                    f"(process wall {res['wall']:.2f} s), Mitsuba render {mi_render[-1]:.2f} s")
            if args.envmap:
                er = run_lightprobe(args.bin, args.scene, Path(tmp) / f"lp_env{r}", spp,
                                    args.threads, ["--envmap", env_ron, "--no-sphere-lights"])
                if er["json"].get("lights") or not er["json"].get("envmap"):
                    raise RuntimeError("the envmap run did not render what was asked: "
                                       f"lights {er['json'].get('lights')}, envmap "
                                       f"{er['json'].get('envmap')}")
                env_lp_render.append(er["render"])
                env_lp_wall.append(er["wall"])
                env_lp_views.append({v["view"]: v["seconds"] for v in er["json"]["views"]})
                t0 = time.perf_counter()
                for v in views:
                    S_env.render(v, seed=r + 1)
                env_mi_render.append(time.perf_counter() - t0)
                line += (f"; envmap: lightprobe {er['render']:.2f} s, Mitsuba "
                         f"{env_mi_render[-1]:.2f} s")
            print(line)

    med = statistics.median
    lp_sps = samples / med(lp_render)
    lp_sps_wall = samples / med(lp_wall)
    mi_sps = samples / med(mi_render)
    mi_sps_first = samples / first_total
    load_after = os.getloadavg()
    result = {
        "scene": str(args.scene),
        "triangles": desc["triangles"],
        "width": w, "height": h, "spp": spp, "views": views,
        "max_bounces": st["max_bounces"], "samples_per_run": samples,
        "repeat": args.repeat, "cpus": os.cpu_count(),
        "loadavg_before": load_before, "loadavg_after": load_after,
        "lightprobe": {
            "threads": lp_threads,
            "render_seconds": lp_render, "wall_seconds": lp_wall,
            "view_seconds": lp_views,
            "median_render_seconds": med(lp_render), "median_wall_seconds": med(lp_wall),
            "samples_per_second": lp_sps, "samples_per_second_wall": lp_sps_wall,
        },
        "mitsuba": {
            "version": mi.__version__, "variant": variant, "threads": dr.thread_count(),
            "integrator": "path (MIS), max_depth = max_bounces + 1, no Russian roulette",
            "scene_build_seconds": build_s,
            "first_render_seconds": first_total, "first_render_view_seconds": first,
            "render_seconds": mi_render, "median_render_seconds": med(mi_render),
            "view_seconds": mi_views,
            "samples_per_second": mi_sps, "samples_per_second_first": mi_sps_first,
        },
        # primary: render time vs warm render time; both exclude scene loading/BVH
        "ratio_lightprobe_over_mitsuba": lp_sps / mi_sps,
        # whole lightprobe process vs Mitsuba's first (JIT-compiling) render
        "ratio_lightprobe_wall_over_mitsuba_first": lp_sps_wall / mi_sps_first,
    }
    if args.envmap:
        env_sps = samples / med(env_lp_render)
        env_mi_sps = samples / med(env_mi_render)
        result["envmap"] = env_info
        result["lightprobe_envmap"] = {
            "render_seconds": env_lp_render, "wall_seconds": env_lp_wall,
            "view_seconds": env_lp_views,
            "median_render_seconds": med(env_lp_render),
            "median_wall_seconds": med(env_lp_wall),
            "samples_per_second": env_sps,
            "samples_per_second_wall": samples / med(env_lp_wall),
        }
        result["mitsuba_envmap"] = {
            "scene_build_seconds": env_build_s, "first_render_seconds": env_first,
            "render_seconds": env_mi_render, "median_render_seconds": med(env_mi_render),
            "samples_per_second": env_mi_sps,
        }
        # the goal: envmap sampling must not slow lightprobe much (close to 1)
        result["ratio_lightprobe_envmap_over_sphere"] = env_sps / lp_sps
        result["ratio_mitsuba_envmap_over_sphere"] = env_mi_sps / mi_sps
        result["ratio_lightprobe_over_mitsuba_envmap"] = env_sps / env_mi_sps
    # per view: a pixel whose rays can meet no geometry ("blind": lightprobe's coverage
    # leaves it out) costs lightprobe nothing and Mitsuba little, yet counts as samples
    per_view = {}
    for v in views:
        t_lp, t_mi = med(d[v] for d in lp_views), med(d[v] for d in mi_views)
        per_view[v] = {"blind_pixel_fraction": 1.0 - coverage[v],
                       "lightprobe_seconds": t_lp, "mitsuba_seconds": t_mi,
                       "lightprobe_samples_per_second": w * h * spp / t_lp,
                       "mitsuba_samples_per_second": w * h * spp / t_mi,
                       "ratio_lightprobe_over_mitsuba": t_mi / t_lp}
    result["per_view"] = per_view
    print(f"\nper view (median of {args.repeat}; blind pixels see no geometry):")
    print(f"  {'view':12s} {'blind':>6s} {'lightprobe':>12s} {'Mitsuba':>12s} {'ratio':>6s}")
    for v, p in per_view.items():
        print(f"  {v:12s} {100 * p['blind_pixel_fraction']:5.0f}% "
              f"{p['lightprobe_samples_per_second'] / 1e6:8.2f} M/s "
              f"{p['mitsuba_samples_per_second'] / 1e6:8.2f} M/s "
              f"{p['ratio_lightprobe_over_mitsuba']:6.2f}")
    print(f"\nall views, median of {args.repeat}:")
    print(f"  lightprobe  {lp_sps / 1e6:8.2f} M samples/s  (render {med(lp_render):.2f} s; "
          f"whole process {lp_sps_wall / 1e6:.2f} M samples/s, {med(lp_wall):.2f} s; "
          f"{lp_threads} threads)")
    print(f"  Mitsuba     {mi_sps / 1e6:8.2f} M samples/s  (render {med(mi_render):.2f} s; "
          f"first render incl. JIT {mi_sps_first / 1e6:.2f} M samples/s, {first_total:.2f} s)")
    print(f"  ratio lightprobe / Mitsuba: {result['ratio_lightprobe_over_mitsuba']:.3f} "
          f"(lightprobe whole process / Mitsuba first render: "
          f"{result['ratio_lightprobe_wall_over_mitsuba_first']:.3f})")
    if args.envmap:
        print(f"  {args.envmap_rings}-ring envmap ({env_info['cells']} cells), no sphere lights:")
        print(f"    lightprobe {env_sps / 1e6:8.2f} M samples/s  (render "
              f"{med(env_lp_render):.2f} s) vs {lp_sps / 1e6:.2f} under the sphere lights: "
              f"envmap / sphere = {result['ratio_lightprobe_envmap_over_sphere']:.3f}")
        print(f"    Mitsuba    {env_mi_sps / 1e6:8.2f} M samples/s  (render "
              f"{med(env_mi_render):.2f} s) vs {mi_sps / 1e6:.2f}: envmap / sphere = "
              f"{result['ratio_mitsuba_envmap_over_sphere']:.3f}; lightprobe / Mitsuba under "
              f"the envmap {result['ratio_lightprobe_over_mitsuba_envmap']:.3f}")
    if load_before[0] > 0.5:
        # (only the load before counts: the benchmark itself adds ~1 per thread)
        print(f"  note: 1-min load average was {load_before[0]:.2f} on {os.cpu_count()} CPUs "
              f"before the run: other work may have slowed both tools (the ratio, from "
              f"interleaved runs, is more robust than the absolute numbers)")
    write_result(result, args.json)
    return 0


if __name__ == "__main__":
    sys.exit(main())
