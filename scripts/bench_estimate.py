#!/usr/bin/env python3
"""Time-to-error benchmark of envmap estimation: lightprobe vs Mitsuba 3, one run.

(Also lightprobe's finite-distance sphere-light model, beside both: see
"Sphere lights" below.)

Both tools estimate the environment lighting that explains the same reference
images (default: the bundled tabletop, 2 views at 128x96, rendered once by
lightprobe `render-reference` from the sidecar's sphere lights at the
sidecar's settings: 512 spp, max_bounces 2, seed 1). Every error below is
relMAE = sum|x - r| / sum|r| over the references' geometry mask (alpha > 0),
RGB, averaged over the views, of a FRESH full-quality re-render (sidecar spp,
a seed used nowhere else) of the estimated lighting -- the metric lightprobe's
report.json calls `rel_mae`.

lightprobe: `estimate --reference REFDIR --rings 9` (the benchmark's setting),
  timed from outside (process wall, max RSS by wait4) and from report.json
  (timings.fit_seconds = transport + solve; total_seconds; memory.peak_bytes).
  The same at --spp 64/128/256 (the transport's total spp budget, over its
  SMC rounds; the re-render stays at the sidecar's spp) gives more (time,
  error) points, and --rings 25 once gives
  the peak memory. The whole process also renders a noise-floor pair and the
  re-render for its own report: "process wall excl. evaluation" subtracts
  timings.noise_floor_seconds + rerender_seconds, like Mitsuba's clock below
  excludes its evaluations.
Sphere lights (unless --spheres 0): `estimate --reference REFDIR --rings 9
  --model spheres:K` (default K = 2, the bundled scene's number of true
  lights), --lp-repeat times (median times), after the envmap runs. The model:
  K sphere lights started from the best set of K candidate lights (the 9-ring
  envmap estimate's bright cells and an even scan of directions), a distance
  search along each, then Levenberg-Marquardt on centres and radii (radiances
  solved exactly) and a direct search on each light's apparent size. Its error is report.json spheres.rel_mae (the
  same metric: a fresh full-quality re-render of the fitted lights); its time,
  the model's stand-alone cost, is timings.fit_seconds (the envmap fit it
  starts from) + spheres.fit_seconds (distance search + LM), excluding the
  noise floor and both re-renders (process wall, with and without them, is
  recorded too). Also recorded per run: the envmap's relMAE and the noise
  floor of the same process, renders, LM iterations, each fitted light's
  status (identified / distance unidentified / merged / no contribution) and,
  per true light, its recovery (centre error in m and as a fraction of its
  distance, power ratio, radius vs the true one). Beside Mitsuba's envmap fit:
  Mitsuba's best relMAE over its resolutions and the optimisation time at
  which it first came within 2% (relative) of that best -- its plateau; a
  checkpoint, so up to --mi-eval-every steps late, and if the best is the last
  checkpoint Mitsuba was still improving and the plateau is only where this
  run stopped (reported).
Mitsuba 3 (llvm_ad_rgb): the same scene (scripts/mitsuba_scene.py: meshes,
  materials, both cameras; no sphere lights) lit by an `envmap` emitter whose
  W x H lat-long bitmap is optimised: a latent (H, W, 3) tensor, padded into
  the emitter's `data` parameter (mi.traverse key `envmap.data`, shape
  (H, W+2, 3) in Mitsuba 3.9: one wrap-around column each side, which the
  emitter overwrites from the interior columns on update; padding by gather
  keeps their gradient). Initialised to a constant that matches the
  references' mean colour (a 32-spp render under a unit envmap, timed), Adam
  (mi.ad.Adam, --mi-lr), loss = mean over views of a relMAE-normalised L2
  (default) or L1 of the masked RGB pixels, `prb` integrator, max_depth =
  max_bounces + 1, no Russian roulette, hide_emitters, --mi-spp per view and
  step, decorrelated primal/adjoint seeds (seed_grad), parameter clamped to
  >= 0 after every step. Every --mi-eval-every steps the current envmap is
  rendered with the `path` integrator (the one scripts/check_mitsuba*.py
  validate against lightprobe) at the references' spp with fresh seeds and
  its relMAE recorded against the cumulative optimisation wall time (JIT
  compilation included; scene building and the evaluations excluded).
Cross-check (unless --no-crosscheck): lightprobe's envmap.exr (9 rings, 512
  spp) rendered by Mitsuba and scored the same way must give lightprobe's own
  rel_mae (its report is not trusted blindly). The same render, fresh seeds
  per map, of every lightprobe envmap run the time-to-error uses (main and
  --curve-spp) gives each point's rel_mae_by_mitsuba: Mitsuba's `independent`
  sampler is noisier at equal spp than lightprobe's stratified one, so part
  of lightprobe's lower own-render error is evaluation noise, not the map.

Time-to-error: target = lightprobe's relMAE at 9 rings / 512 spp, or Mitsuba's
best if it never gets there. Each tool's time = its first point at or below
the target (lightprobe: smallest fit_seconds among its runs; Mitsuba: the
first evaluation checkpoint, so up to --mi-eval-every steps late; the previous
checkpoint is reported as the lower bound). Ratio = Mitsuba / lightprobe. Same
evaluator (unless --no-crosscheck): time_to_error_same_evaluator, the same
rules with lightprobe's errors taken from rel_mae_by_mitsuba (Mitsuba's curve
is Mitsuba-rendered already), so Mitsuba renders both tools' maps. Goals from
the project, each reported as met or not: lightprobe >= 20x faster at equal or
lower error (by own re-renders and by the same evaluator), lightprobe under
5 s wall clock, peak memory at 25 rings under 1 GiB; and the sphere model's for the
sphere model: under 15 s (median envmap fit + sphere fit; its first version
took 34 s).

Writes OUT/estimate_vs_mitsuba.png (relMAE vs time, log axes; the sphere
model is one star: median model seconds, its relMAE) and
OUT/bench_estimate.json (every number, the lightprobe build measured, and
how many cores other processes used during each timed run: /proc/stat minus
our own CPU time). On an idle 2-core machine the defaults took ~1.5 min
before the sphere runs, with --mi-res 32x16,64x32 --lp-repeat 3 ~2.5 min;
each sphere run adds roughly 15 s (an estimate: the model's ~11 s plus the
process's noise floor and re-renders). A concurrent build skews
timings: --wait-idle S waits up to S seconds before every timed run for
other processes to use < 0.2 cores. lr 0.3 / L2 / 16 spp: lr 0.1 is slower,
0.6 and 1.0 reach lightprobe's error in the same number of steps (measured);
L1 ends slightly worse.

Usage: .venv/bin/python scripts/bench_estimate.py [--out DIR] [--mi-res 32x16,64x32]
       [--mi-steps 200] [--mi-spp 16] [--mi-lr 0.3] [--mi-loss l2] [--mi-eval-every 10]
       [--curve-spp 64,128,256] [--lp-repeat 3] [--big-rings 25] [--spheres 2]
       [--wait-idle 600]
       [--quick]                          (smoke test, ~40 s + one sphere run)
       --replot OUT/bench_estimate.json --out OUT   (redraw the chart only)
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import mitsuba_scene as ms  # noqa: E402

GIB = 1 << 30


def log(msg: str = "") -> None:
    print(msg, flush=True)


def load() -> list[float]:
    return [round(x, 2) for x in os.getloadavg()]


def _cpu_now() -> tuple[float, float, float]:
    """(wall, busy CPU-seconds of the whole machine, CPU-seconds of this
    process and its reaped children)."""
    with open("/proc/stat") as f:
        v = [int(x) for x in f.readline().split()[1:]]
    hz = os.sysconf("SC_CLK_TCK")
    idle = v[3] + (v[4] if len(v) > 4 else 0)          # idle + iowait
    t = os.times()
    return (time.perf_counter(), (sum(v[:8]) - idle) / hz,
            t.user + t.system + t.children_user + t.children_system)


def wait_idle(max_seconds: float, threshold: float = 0.2, window: float = 5.0) -> dict:
    """Wait (up to max_seconds) for a window in which other processes use
    less than `threshold` cores; returns what was seen."""
    t0 = time.perf_counter()
    while True:
        with CpuMonitor() as cm:
            time.sleep(window)
        busy = cm.result["other_cores"]
        waited = time.perf_counter() - t0
        if busy < threshold or waited >= max_seconds:
            return {"waited_seconds": waited, "other_cores_last_window": busy,
                    "idle": busy < threshold}


class CpuMonitor:
    """How many cores other processes kept busy while we measured: the
    machine's busy time (/proc/stat) minus our own (and our children's)."""

    def __enter__(self):
        self.a = _cpu_now()
        return self

    def __exit__(self, *exc):
        b = _cpu_now()
        wall = b[0] - self.a[0]
        self.result = {"wall": wall, "own_cores": (b[2] - self.a[2]) / wall,
                       "other_cores": max(0.0, (b[1] - self.a[1]) - (b[2] - self.a[2])) / wall,
                       "loadavg_end": load()}
        return False


# --------------------------------------------------------------------------
# lightprobe
# --------------------------------------------------------------------------

def wait_for_binary(path: Path, seconds: float = 120.0) -> None:
    """The binary vanishes for a moment while a concurrent build relinks it."""
    deadline = time.monotonic() + seconds
    while not (path.is_file() and os.access(path, os.X_OK)):
        if time.monotonic() > deadline:
            raise SystemExit(f"{path} not found (cargo build --release)")
        time.sleep(2)


def run_timed(cmd: list) -> dict:
    """Run a command; wall time and the child's own max RSS and CPU time (wait4)."""
    cmd = [str(c) for c in cmd]
    wait_for_binary(Path(cmd[0]))
    with tempfile.TemporaryFile("w+") as fo, tempfile.TemporaryFile("w+") as fe:
        t0 = time.perf_counter()
        p = subprocess.Popen(cmd, stdout=fo, stderr=fe, stdin=subprocess.DEVNULL)
        _, status, ru = os.wait4(p.pid, 0)
        wall = time.perf_counter() - t0
        p.returncode = os.waitstatus_to_exitcode(status)   # reaped here, not by Popen
        fo.seek(0)
        fe.seek(0)
        out, err = fo.read(), fe.read()
    if p.returncode != 0:
        raise RuntimeError(f"{' '.join(cmd)} failed ({p.returncode}):\n{err}")
    return {"wall_seconds": wall, "max_rss_bytes": ru.ru_maxrss * 1024, "stdout": out,
            "user_seconds": ru.ru_utime, "sys_seconds": ru.ru_stime}


def lp_estimate(bin_: Path, scene: Path, ref: Path, out: Path, rings: int,
                spp: int | None, wait: float = 0.0, extra: list | None = None) -> dict:
    """One timed `lightprobe estimate`; extra: more arguments (e.g. --model spheres:2)."""
    idle = wait_idle(wait) if wait else None
    cmd = [bin_, "estimate", scene, "--out", out, "--reference", ref, "--rings", rings,
           "--quiet", "--json"]
    if spp:
        cmd += ["--spp", spp]
    cmd += list(extra or [])
    with CpuMonitor() as cm:
        r = run_timed(cmd)
    rep = json.loads((out / "report.json").read_text())
    t = rep["timings"]
    evaluation = t.get("noise_floor_seconds", 0.0) + t.get("rerender_seconds", 0.0)
    res = {
        "rings": rings, "cells": rep["cells"], "transport_spp": rep["transport_spp"],
        "rounds": rep.get("rounds"), "solver": rep.get("solver"),
        "rel_mae": rep["rel_mae"], "noise_floor_rel_mae": rep["noise_floor_rel_mae"],
        "view_rel_mae": {v["view"]: v["estimate"]["rel_mae"] for v in rep["views"]},
        "fit_seconds": t["fit_seconds"], "total_seconds": t["total_seconds"],
        "timings": t, "process_wall_seconds": r["wall_seconds"],
        "process_wall_excl_evaluation_seconds": r["wall_seconds"] - evaluation,
        "process_cpu_seconds": r["user_seconds"] + r["sys_seconds"],
        "peak_bytes": rep["memory"]["peak_bytes"], "memory": rep["memory"],
        "max_rss_bytes": r["max_rss_bytes"], "threads": rep.get("threads"),
        "light_recovery": rep.get("light_recovery"), "out": str(out),
        "cpu": cm.result, "wait_idle": idle,
    }
    if rep.get("spheres"):                      # --model spheres:K (null for the envmap)
        res["model"], res["spheres"] = rep.get("model"), rep["spheres"]
    return res


def run_lightprobe_suite(args, ref: Path, work: Path) -> dict:
    res = {"load_before": load()}
    main_runs = []
    for k in range(args.lp_repeat):
        r = lp_estimate(args.bin, args.scene, ref, work / f"lp_r{args.rings}_main{k}",
                        args.rings, None)
        main_runs.append(r)
        log(f"  lightprobe rings {args.rings} spp {r['transport_spp']} (run {k + 1}/"
            f"{args.lp_repeat}): relMAE {r['rel_mae']:.4f} fit {r['fit_seconds']:.2f} s, "
            f"report total {r['total_seconds']:.2f} s, process wall "
            f"{r['process_wall_seconds']:.2f} s (excl. evaluation "
            f"{r['process_wall_excl_evaluation_seconds']:.2f} s), peak "
            f"{r['peak_bytes'] / 2**20:.0f} MiB; other processes used "
            f"{r['cpu']['other_cores']:.2f} cores meanwhile")
    med = lambda key: statistics.median(r[key] for r in main_runs)  # noqa: E731
    main = dict(main_runs[0])
    for key in ("fit_seconds", "total_seconds", "process_wall_seconds",
                "process_wall_excl_evaluation_seconds"):
        main[key] = med(key)
        main[key + "_runs"] = [r[key] for r in main_runs]
    errs = {r["rel_mae"] for r in main_runs}
    if len(errs) > 1:
        log(f"  note: repeated runs gave different relMAE {sorted(errs)} (not deterministic)")
    res["main"] = main
    curve = []
    for spp in args.curve_spp:
        if spp == main["transport_spp"]:
            continue
        r = lp_estimate(args.bin, args.scene, ref, work / f"lp_r{args.rings}_spp{spp}",
                        args.rings, spp, args.wait_idle)
        curve.append(r)
        log(f"  lightprobe rings {args.rings} spp {spp}: relMAE {r['rel_mae']:.4f} fit "
            f"{r['fit_seconds']:.2f} s, process wall {r['process_wall_seconds']:.2f} s; other "
            f"processes {r['cpu']['other_cores']:.2f} cores")
    curve.append(main)
    res["curve"] = sorted(curve, key=lambda r: r["transport_spp"])
    if args.big_rings:
        r = lp_estimate(args.bin, args.scene, ref, work / f"lp_r{args.big_rings}",
                        args.big_rings, None, args.wait_idle)
        res["big"] = r
        log(f"  lightprobe rings {args.big_rings} ({r['cells']} cells): relMAE "
            f"{r['rel_mae']:.4f} fit {r['fit_seconds']:.2f} s, process wall "
            f"{r['process_wall_seconds']:.2f} s, memory.peak_bytes {r['peak_bytes']:,} "
            f"({r['peak_bytes'] / GIB:.3f} GiB; process max RSS {r['max_rss_bytes']:,}); other "
            f"processes {r['cpu']['other_cores']:.2f} cores")
    res["load_after"] = load()
    return res


SPHERE_GOAL_SECONDS = 15.0     # the sphere model under 15 s


def sphere_run(r: dict) -> dict:
    """One `--model spheres:K` run (an lp_estimate record): the numbers the
    benchmark keeps. Model seconds = envmap fit (its start) + sphere fit."""
    s, t = r["spheres"], r["timings"]
    evaluation = (t.get("noise_floor_seconds", 0.0) + (t.get("rerender_seconds") or 0.0)
                  + (s.get("rerender_seconds") or 0.0))
    return {
        "model": r.get("model"), "rel_mae": s["rel_mae"],
        "noise_floor_rel_mae": r["noise_floor_rel_mae"], "envmap_rel_mae": r["rel_mae"],
        "envmap_fit_seconds": r["fit_seconds"], "sphere_fit_seconds": s["fit_seconds"],
        "model_seconds": r["fit_seconds"] + s["fit_seconds"],
        "process_wall_seconds": r["process_wall_seconds"],
        "process_wall_excl_evaluation_seconds": r["process_wall_seconds"] - evaluation,
        "report_total_seconds": r["total_seconds"], "rerender_seconds": s.get("rerender_seconds"),
        "renders": s.get("renders"), "iterations": s.get("iterations"),
        "fit_rel_mae_binned": s.get("fit_rel_mae_binned"),
        "lights": s.get("lights"), "recovery": s.get("recovery"),
        "rings": r["rings"], "cells": r["cells"], "transport_spp": r["transport_spp"],
        "peak_bytes": r["peak_bytes"], "max_rss_bytes": r["max_rss_bytes"],
        "threads": r["threads"], "out": r["out"], "cpu": r["cpu"], "wait_idle": r["wait_idle"],
    }


def run_sphere_suite(args, ref: Path, work: Path) -> dict:
    """`estimate --model spheres:K`, --lp-repeat times; median times."""
    model = f"spheres:{args.spheres}"
    res = {"load_before": load()}
    runs = []
    for k in range(args.lp_repeat):
        r = lp_estimate(args.bin, args.scene, ref, work / f"lp_r{args.rings}_spheres{args.spheres}_{k}",
                        args.rings, None, args.wait_idle, ["--model", model])
        if (r.get("spheres") or {}).get("rel_mae") is None:
            raise RuntimeError(f"lightprobe estimate --model {model}: no spheres.rel_mae in "
                               f"{r['out']}/report.json")
        s = sphere_run(r)
        runs.append(s)
        log(f"  lightprobe {model} (run {k + 1}/{args.lp_repeat}): relMAE {s['rel_mae']:.4f} "
            f"(envmap {s['envmap_rel_mae']:.4f}, noise floor {s['noise_floor_rel_mae']:.4f}); "
            f"envmap fit {s['envmap_fit_seconds']:.2f} s + sphere fit "
            f"{s['sphere_fit_seconds']:.2f} s = {s['model_seconds']:.2f} s, {s['renders']} "
            f"renders, {s['iterations']} iterations; process wall "
            f"{s['process_wall_seconds']:.2f} s (excl. evaluation "
            f"{s['process_wall_excl_evaluation_seconds']:.2f} s); other processes used "
            f"{s['cpu']['other_cores']:.2f} cores meanwhile")
    res.update(runs[0])
    for key in ("envmap_fit_seconds", "sphere_fit_seconds", "model_seconds",
                "process_wall_seconds", "process_wall_excl_evaluation_seconds",
                "report_total_seconds", "rerender_seconds"):
        vals = [r[key] for r in runs if r[key] is not None]
        res[key] = statistics.median(vals) if vals else None
        res[key + "_runs"] = [r[key] for r in runs]
    errs = {r["rel_mae"] for r in runs}
    if len(errs) > 1:
        log(f"  note: repeated {model} runs gave different relMAE {sorted(errs)} "
            f"(not deterministic); the first run's is reported")
    res.update({"model": model, "k": args.spheres, "repeats": len(runs), "runs": runs,
                "goal_seconds": SPHERE_GOAL_SECONDS,
                "goal_under_15_s_met": res["model_seconds"] < SPHERE_GOAL_SECONDS,
                "load_after": load()})
    return res


def binary_provenance(path: Path) -> dict:
    """Which build was measured (the binary is rebuilt while people work)."""
    import hashlib
    wait_for_binary(path)
    st = path.stat()
    h = hashlib.sha256(path.read_bytes()).hexdigest()
    try:
        head = subprocess.run(["git", "-C", str(ms.REPO), "rev-parse", "--short", "HEAD"],
                              capture_output=True, text=True).stdout.strip()
        dirty = subprocess.run(["git", "-C", str(ms.REPO), "status", "--porcelain", "--", "src"],
                               capture_output=True, text=True).stdout.strip()
        head += " (src/ modified)" if dirty else ""
    except OSError:
        head = None
    return {"path": str(path), "mtime": time.strftime("%Y-%m-%d %H:%M:%S", time.localtime(st.st_mtime)),
            "sha256": h, "git_head": head}


# --------------------------------------------------------------------------
# Mitsuba
# --------------------------------------------------------------------------

def read_rgba(path: Path) -> np.ndarray:
    import mitsuba as mi
    a = np.array(mi.Bitmap(str(path)), dtype=np.float32)
    assert a.ndim == 3 and a.shape[2] == 4, (path, a.shape)
    return a


def rel_mae(img: np.ndarray, ref: np.ndarray, mask: np.ndarray) -> float:
    return float(np.abs(img[mask][:, :3] - ref[mask][:, :3]).sum()
                 / np.abs(ref[mask][:, :3]).sum())


class MitsubaFit:
    """Envmap optimisation in Mitsuba; see the module docstring."""

    def __init__(self, args, desc, meshes, refs: dict, width: int, height: int):
        import drjit as dr
        import mitsuba as mi
        self.dr, self.mi = dr, mi
        self.args, self.refs, self.W, self.H = args, refs, width, height
        self.views = list(refs)
        self.masks = {v: refs[v][..., 3] > 0 for v in self.views}
        st = desc["settings"]
        self.eval_spp = args.mi_eval_spp or st["spp"]
        self.max_depth = st["max_bounces"] + 1
        t0 = time.perf_counter()
        self.S = ms.build_scene(args.scene, args.bin, desc=desc, meshes=meshes,
                                envmap=np.ones((height, width, 3), np.float32),
                                sphere_lights=False, spp=args.mi_spp)
        self.path = self.S.scene.integrator()          # validated against lightprobe
        try:
            self.prb = mi.load_dict({"type": args.mi_integrator, "max_depth": self.max_depth,
                                     "rr_depth": self.max_depth + 100, "hide_emitters": True})
            self.integrator_name = args.mi_integrator
        except Exception as e:  # noqa: BLE001
            log(f"  {args.mi_integrator} unavailable ({e}); using path")
            self.prb, self.integrator_name = self.path, "path"
        self.params = mi.traverse(self.S.scene)
        self.key = "envmap.data"
        shape = tuple(self.params[self.key].shape)
        if shape != (height, width + 2, 3):
            raise SystemExit(f"unexpected {self.key} shape {shape} (Mitsuba version?)")
        cols = np.concatenate([[width - 1], np.arange(width), [0]])
        idx = (np.arange(height)[:, None, None] * width * 3 + cols[None, :, None] * 3
               + np.arange(3)[None, None, :]).ravel().astype(np.uint32)
        self.pad_index = mi.UInt32(idx)
        self.build_seconds = time.perf_counter() - t0
        # per view: reference, L1 weights (relMAE), L2 weights (relMSE-like)
        self.w = {}
        for v in self.views:
            r = refs[v]
            m = np.repeat(self.masks[v][..., None], 4, -1)
            m[..., 3] = False
            s1 = float(np.abs(r[m]).sum())
            mean = float(r[m].mean())
            self.w[v] = (mi.Float(r.ravel()),
                         mi.Float((m / s1).astype(np.float32).ravel()),
                         mi.Float((m / (m.sum() * mean * mean)).astype(np.float32).ravel()))

    def pad(self, x):
        mi, dr = self.mi, self.dr
        return mi.TensorXf(dr.gather(mi.Float, x.array, self.pad_index),
                           shape=(self.H, self.W + 2, 3))

    def set_envmap(self, x) -> None:
        self.params[self.key] = self.pad(x)
        self.params.update()

    def evaluate(self, x, k: int) -> dict:
        """relMAE of a fresh full-quality render of envmap x (not timed)."""
        mi, dr = self.mi, self.dr
        with dr.suspend_grad():
            self.set_envmap(mi.TensorXf(dr.detach(x)))
            per_view = {}
            for i, v in enumerate(self.views):
                img = np.array(mi.render(self.S.scene, sensor=self.S.sensors[v],
                                         integrator=self.path, spp=self.eval_spp,
                                         seed=1_000_000 + 2 * k + i), dtype=np.float32)
                per_view[v] = rel_mae(img, self.refs[v], self.masks[v])
        return {"rel_mae": float(np.mean(list(per_view.values()))), "views": per_view}

    def run(self) -> dict:
        mi, dr, a = self.mi, self.dr, self.args
        t0 = time.perf_counter()
        if a.mi_init == "match":
            # constant matching the references' mean colour: one 32-spp render
            # under a unit envmap (timed: it is part of Mitsuba's method)
            ratios = []
            for i, v in enumerate(self.views):
                img = np.array(mi.render(self.S.scene, sensor=self.S.sensors[v],
                                         integrator=self.path, spp=32, seed=999_000 + i))
                m = self.masks[v]
                ratios.append(self.refs[v][m][:, :3].mean(0)
                              / np.maximum(img[m][:, :3].mean(0), 1e-8))
            c = np.mean(ratios, 0).astype(np.float32)
        else:
            c = np.full(3, float(a.mi_init), np.float32)
        opt = mi.ad.Adam(lr=a.mi_lr)
        opt["x"] = mi.TensorXf(np.ascontiguousarray(
            np.broadcast_to(c, (self.H, self.W, 3))))
        clock = time.perf_counter() - t0
        curve = []

        def checkpoint(step: int, loss: float | None) -> None:
            t = time.perf_counter()
            e = self.evaluate(opt["x"], len(curve))
            curve.append({"step": step, "seconds": clock, "loss": loss,
                          "eval_seconds": time.perf_counter() - t, **e})

        checkpoint(0, None)
        step_seconds = []
        loss_val = None
        for it in range(1, a.mi_steps + 1):
            t = time.perf_counter()
            self.set_envmap(opt["x"])
            loss = mi.Float(0.0)
            for i, v in enumerate(self.views):
                s = 4 * it + 2 * i
                img = mi.render(self.S.scene, self.params, sensor=self.S.sensors[v],
                                integrator=self.prb, spp=a.mi_spp, seed=s, seed_grad=s + 1)
                ref, w1, w2 = self.w[v]
                d = img.array - ref
                term = dr.sum(w1 * dr.abs(d)) if a.mi_loss == "l1" else dr.sum(w2 * d * d)
                loss = loss + term / len(self.views)
            dr.backward(loss)
            opt.step()
            opt["x"] = dr.maximum(opt["x"], 0.0)
            dr.eval(opt["x"])
            dr.sync_thread()
            dt = time.perf_counter() - t
            step_seconds.append(dt)
            clock += dt
            if it % a.mi_eval_every == 0 or it == a.mi_steps:
                loss_val = float(np.array(loss).ravel()[0])
                checkpoint(it, loss_val)
                cp = curve[-1]
                log(f"    step {it:4d}  opt time {clock:7.2f} s  relMAE {cp['rel_mae']:.4f}  "
                    f"(loss {loss_val:.4g}, eval {cp['eval_seconds']:.1f} s, load {load()[0]})")
        best = min(curve, key=lambda c: c["rel_mae"])
        x = np.array(opt["x"])
        return {
            "resolution": [self.W, self.H], "integrator": self.integrator_name,
            "eval_integrator": "path", "max_depth": self.max_depth, "spp_per_step": a.mi_spp,
            "eval_spp": self.eval_spp, "steps": a.mi_steps, "lr": a.mi_lr, "loss": a.mi_loss,
            "init": a.mi_init, "init_constant": c.tolist(),
            "scene_build_seconds": self.build_seconds,
            "first_step_seconds": step_seconds[0] if step_seconds else None,
            "median_step_seconds": statistics.median(step_seconds) if step_seconds else None,
            "optimisation_seconds": clock, "curve": curve,
            "best": {k: best[k] for k in ("step", "seconds", "rel_mae")},
            "final": {k: curve[-1][k] for k in ("step", "seconds", "rel_mae")},
            "envmap_max": float(x.max()), "envmap_mean": float(x.mean()),
            "threads": dr.thread_count(),
        }


def crosscheck(args, desc, meshes, refs: dict, envmap_exr: Path, lp_rel_mae: float,
               k: int = 0) -> dict:
    """lightprobe's exported estimate rendered by Mitsuba, scored the same way;
    k: which map (fresh seeds per map; k = 0 is the main run's)."""
    import mitsuba as mi
    S = ms.build_scene(args.scene, args.bin, desc=desc, meshes=meshes, envmap=envmap_exr,
                       sphere_lights=False)
    per_view = {}
    seed0 = 2_000_000 + len(refs) * k
    for i, v in enumerate(refs):
        img = np.array(mi.render(S.scene, sensor=S.sensors[v], seed=seed0 + i),
                       dtype=np.float32)
        per_view[v] = rel_mae(img, refs[v], refs[v][..., 3] > 0)
    mean = float(np.mean(list(per_view.values())))
    return {"envmap": str(envmap_exr), "spp": S.spp, "seed_first": seed0, "views": per_view,
            "rel_mae": mean, "lightprobe_rel_mae": lp_rel_mae, "difference": mean - lp_rel_mae}


def crosscheck_all(args, desc, meshes, refs: dict, lp: dict) -> dict:
    """crosscheck() of every lightprobe envmap run the time-to-error uses (the
    main run first, k = 0, then the --curve-spp runs); sets each run's
    rel_mae_by_mitsuba. Returns the main run's cross-check with every point's
    under "per_lightprobe_point"."""
    main = lp["main"]
    runs = [main] + [r for r in lp["curve"] if r is not main]
    points = []
    for k, r in enumerate(runs):
        t0 = time.perf_counter()
        c = crosscheck(args, desc, meshes, refs, Path(r["out"]) / "envmap.exr", r["rel_mae"], k)
        c.update({"transport_spp": r["transport_spp"], "main": r is main,
                  "seconds": time.perf_counter() - t0})
        r["rel_mae_by_mitsuba"] = c["rel_mae"]
        points.append(c)
        log(f"cross-check: lightprobe's envmap.exr (spp {r['transport_spp']}"
            f"{', main run' if r is main else ''}) rendered by Mitsuba ({c['spp']} spp): relMAE "
            f"{c['rel_mae']:.4f} vs lightprobe's own {c['lightprobe_rel_mae']:.4f} (difference "
            f"{c['difference']:+.4f}; {c['seconds']:.1f} s)")
    out = dict(points[0])
    out["per_lightprobe_point"] = sorted(points, key=lambda c: c["transport_spp"])
    return out


# --------------------------------------------------------------------------
# time-to-error, chart
# --------------------------------------------------------------------------

def first_at_or_below(points: list[tuple[float, float]], target: float):
    """(time, previous time) of the first (time, err) with err <= target, in time order."""
    prev = 0.0
    for t, e in sorted(points):
        if e <= target:
            return t, prev
        prev = t
    return None, None


def time_to_error(lp: dict, mitsuba: list[dict], key: str = "rel_mae") -> dict | None:
    """key: lightprobe's error per run -- "rel_mae" (its own re-render) or
    "rel_mae_by_mitsuba" (Mitsuba's render of its map: the same evaluator as
    Mitsuba's curve); None if a run lacks it. Pure: recomputed by --replot."""
    if any(r.get(key) is None for r in lp["curve"] + [lp["main"]]):
        return None
    target_lp = lp["main"][key]
    out = {"lightprobe_error": key, "lightprobe_target_rel_mae": target_lp,
           "per_resolution": []}
    for m in mitsuba:
        mi_pts = [(c["seconds"], c["rel_mae"]) for c in m["curve"]]
        mi_best = m["best"]["rel_mae"]
        reached = mi_best <= target_lp
        target = target_lp if reached else mi_best
        t_mi, t_mi_prev = first_at_or_below(mi_pts, target)
        lp_fit, _ = first_at_or_below([(r["fit_seconds"], r[key]) for r in lp["curve"]],
                                      target)
        ok = [r for r in lp["curve"] if r[key] <= target]
        lp_run = min(ok, key=lambda r: r["fit_seconds"]) if ok else None
        row = {"resolution": m["resolution"], "target_rel_mae": target,
               "target_is": "lightprobe 9 rings / 512 spp" if reached else "Mitsuba's best",
               "mitsuba_reaches_lightprobe_error": reached,
               "mitsuba_seconds": t_mi, "mitsuba_seconds_previous_checkpoint": t_mi_prev,
               "mitsuba_seconds_incl_scene_build": (t_mi + m["scene_build_seconds"])
               if t_mi is not None else None}
        if lp_run is not None:
            row.update({
                "lightprobe_transport_spp": lp_run["transport_spp"],
                "lightprobe_fit_seconds": lp_fit,
                "lightprobe_process_wall_seconds": lp_run["process_wall_seconds"],
                "lightprobe_process_wall_excl_evaluation_seconds":
                    lp_run["process_wall_excl_evaluation_seconds"],
                "ratio_fit": t_mi / lp_fit if t_mi else None,
                "ratio_process_wall": t_mi / lp_run["process_wall_seconds"] if t_mi else None,
                "ratio_process_wall_excl_evaluation":
                    t_mi / lp_run["process_wall_excl_evaluation_seconds"] if t_mi else None,
            })
        # every lightprobe point: how long Mitsuba needs for the same error
        row["per_lightprobe_point"] = []
        for r in sorted(lp["curve"], key=lambda r: r["transport_spp"]):
            t, tp = first_at_or_below(mi_pts, r[key])
            row["per_lightprobe_point"].append({
                "transport_spp": r["transport_spp"], "rel_mae": r[key],
                "lightprobe_fit_seconds": r["fit_seconds"], "mitsuba_seconds": t,
                "mitsuba_seconds_previous_checkpoint": tp,
                "ratio_fit": t / r["fit_seconds"] if t else None})
        out["per_resolution"].append(row)
    return out


MITSUBA_PLATEAU = 0.02          # "plateau": first checkpoint within 2% (relative) of the best


def sphere_vs_mitsuba(sp: dict, mitsuba: list[dict]) -> dict | None:
    """The sphere model beside Mitsuba's envmap fit: Mitsuba's best relMAE over
    its resolutions, the first checkpoint (any resolution) within
    MITSUBA_PLATEAU of it, and per resolution when (if ever) it reaches the
    sphere model's error. Pure: recomputed by --replot."""
    if not mitsuba:
        return None
    best_m = min(mitsuba, key=lambda m: m["best"]["rel_mae"])
    best = best_m["best"]["rel_mae"]
    near = best * (1 + MITSUBA_PLATEAU)
    t, e, m0 = min(((c["seconds"], c["rel_mae"], m) for m in mitsuba for c in m["curve"]
                    if c["rel_mae"] <= near), key=lambda x: x[0])
    err, secs = sp["rel_mae"], sp["model_seconds"]
    per_res = []
    for m in mitsuba:
        pts = [(c["seconds"], c["rel_mae"]) for c in m["curve"]]
        tp, _ = first_at_or_below(pts, m["best"]["rel_mae"] * (1 + MITSUBA_PLATEAU))
        ts, tsp = first_at_or_below(pts, err)
        per_res.append({
            "resolution": m["resolution"], "best_rel_mae": m["best"]["rel_mae"],
            "best_seconds": m["best"]["seconds"], "plateau_seconds": tp,
            "best_at_last_checkpoint": m["best"]["step"] == m["final"]["step"],
            "seconds_to_sphere_error": ts, "seconds_to_sphere_error_previous_checkpoint": tsp})
    return {
        "plateau_tolerance_relative": MITSUBA_PLATEAU,
        "sphere_rel_mae": err, "sphere_model_seconds": secs,
        "mitsuba_best_rel_mae": best, "mitsuba_best_resolution": best_m["resolution"],
        "mitsuba_best_seconds": best_m["best"]["seconds"],
        # the best at the last checkpoint: Mitsuba was still improving when it stopped
        "mitsuba_best_at_last_checkpoint": best_m["best"]["step"] == best_m["final"]["step"],
        "mitsuba_plateau_seconds": t, "mitsuba_plateau_rel_mae": e,
        "mitsuba_plateau_resolution": m0["resolution"],
        "mitsuba_plateau_seconds_incl_scene_build": t + m0["scene_build_seconds"],
        "sphere_below_mitsuba_best": err < best,
        "error_ratio_mitsuba_best_over_sphere": best / err if err else None,
        "time_ratio_mitsuba_plateau_over_sphere_model": t / secs if secs else None,
        "per_resolution": per_res,
    }


def chart(path: Path, lp: dict, mitsuba: list[dict], tte: dict, meta: dict,
          spheres: dict | None = None) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    fig, ax = plt.subplots(figsize=(10, 8.5 if spheres else 8.2), dpi=120)
    colours = ["tab:blue", "tab:purple", "tab:cyan"]
    for m, col in zip(mitsuba, colours):
        pts = [(c["seconds"], c["rel_mae"]) for c in m["curve"]]
        w, h = m["resolution"]
        b = m["best"]
        ax.plot([p[0] for p in pts], [p[1] for p in pts], "-o", color=col, ms=3, lw=1.6,
                label=f"Mitsuba 3 Adam, {w}x{h} envmap ({m['integrator']}, {m['spp_per_step']} "
                      f"spp/step, lr {m['lr']}, {m['loss'].upper()}); step 0 = init; best "
                      f"{b['rel_mae']:.4f} (step {b['step']}, {b['seconds']:.1f} s)")
    cur = sorted(lp["curve"], key=lambda r: r["transport_spp"])
    ax.plot([r["fit_seconds"] for r in cur], [r["rel_mae"] for r in cur], "s-", color="tab:red",
            ms=7, lw=1.2, label=f"lightprobe estimate, {lp['main']['rings']} rings: fit time "
                                 f"(transport + solve); labels = transport spp")
    for r in cur:
        ax.annotate(f"{r['transport_spp']}", (r["fit_seconds"], r["rel_mae"]),
                    textcoords="offset points", xytext=(6, 4), fontsize=8, color="tab:red")
    mn = lp["main"]
    ax.plot([mn["process_wall_seconds"]], [mn["rel_mae"]], "s", mfc="none", mec="tab:red", ms=8,
            label="lightprobe 512 spp: whole process wall (incl. its own noise-floor and "
                  "re-render)")
    ax.plot([mn["process_wall_excl_evaluation_seconds"]], [mn["rel_mae"]], "D", mfc="none",
            mec="darkred", ms=7, label="lightprobe 512 spp: process wall excl. evaluation")
    if lp.get("big"):
        b = lp["big"]
        ax.plot([b["fit_seconds"]], [b["rel_mae"]], "^", color="darkorange", ms=8,
                label=f"lightprobe {b['rings']} rings, 512 spp (fit time; peak "
                      f"{b['peak_bytes'] / 2**20:.0f} MiB)")
    if spheres:
        sp = spheres
        ax.plot([sp["model_seconds"]], [sp["rel_mae"]], "*", color="tab:green", ms=15,
                mec="darkgreen",
                label=f"lightprobe --model {sp['model']} (sphere lights, finite distance): "
                      f"envmap fit {sp['envmap_fit_seconds']:.1f} s + sphere fit "
                      f"{sp['sphere_fit_seconds']:.1f} s (median of {sp['repeats']}); "
                      f"envmap in the same run {sp['envmap_rel_mae']:.4f}")
        ax.annotate(f"{sp['model']}: {sp['rel_mae']:.4f} in {sp['model_seconds']:.1f} s",
                    (sp["model_seconds"], sp["rel_mae"]), textcoords="offset points",
                    xytext=(-10, 7), ha="right", fontsize=8, color="darkgreen")
    ax.axhline(mn["noise_floor_rel_mae"], color="gray", ls="--", lw=1.2,
               label=f"noise floor (two 512-spp renders of the true lights) "
                     f"{mn['noise_floor_rel_mae']:.4f}")
    ax.axhline(mn["rel_mae"], color="tab:red", ls=":", lw=1.0,
               label=f"target: lightprobe 9 rings / 512 spp relMAE {mn['rel_mae']:.4f}")
    for row, col in zip(tte["per_resolution"], colours):
        if row.get("mitsuba_seconds"):
            ax.axvline(row["mitsuba_seconds"], color=col, ls=":", lw=1)
    ax.set_xscale("log")
    ax.set_yscale("log")
    from matplotlib.ticker import FormatStrFormatter
    ax.yaxis.set_major_formatter(FormatStrFormatter("%.2f"))
    ax.yaxis.set_minor_formatter(FormatStrFormatter("%.2f"))
    ax.xaxis.set_major_formatter(FormatStrFormatter("%g"))
    ax.set_xlabel("wall time, seconds (log); Mitsuba: cumulative optimisation time incl. JIT, "
                  "excl. scene build and evaluations")
    ax.set_ylabel("relMAE (log) of a fresh 512-spp re-render vs the references, mean of views")
    ys = [r["rel_mae"] for r in cur] + [c["rel_mae"] for m in mitsuba for c in m["curve"]]
    lo = min([mn["noise_floor_rel_mae"]] + ([spheres["rel_mae"]] if spheres else []))
    ax.set_ylim(lo * 0.85, max(ys) * 1.12)
    ax.grid(True, which="both", alpha=0.3)
    lines = []
    for row in tte["per_resolution"]:
        w, h = row["resolution"]
        if row.get("ratio_fit"):
            lines.append(f"Mitsuba {w}x{h} -> relMAE {row['target_rel_mae']:.4f} "
                         f"({row['target_is']}): Mitsuba {row['mitsuba_seconds']:.1f} s "
                         f"(dotted line), lightprobe fit {row['lightprobe_fit_seconds']:.2f} s: "
                         f"{row['ratio_fit']:.1f}x (vs lightprobe process wall "
                         f"{row['ratio_process_wall']:.1f}x)")
    vs = (spheres or {}).get("vs_mitsuba")
    if vs:
        lines.append(f"sphere model ({spheres['model']}): relMAE {vs['sphere_rel_mae']:.4f} in "
                     f"{vs['sphere_model_seconds']:.1f} s vs Mitsuba's best "
                     f"{vs['mitsuba_best_rel_mae']:.4f} after {vs['mitsuba_plateau_seconds']:.1f} s "
                     f"(first within {100 * vs['plateau_tolerance_relative']:.0f}% of it"
                     + ("; still improving at its last step)"
                        if vs["mitsuba_best_at_last_checkpoint"] else ")"))
    lines.append("goal: lightprobe >= 20x faster than Mitsuba at equal or lower error, < 5 s wall"
                 + ("; sphere model < 15 s" if spheres else ""))
    lines.append(f"load average during runs: {meta['load_summary']} on {meta['cpus']} CPUs")
    ax.text(0.01, 0.10, "\n".join(lines), transform=ax.transAxes, fontsize=8, va="bottom",
            bbox=dict(boxstyle="round", fc="white", alpha=0.9))
    ax.set_title(f"{'Envmap and sphere-light' if spheres else 'Envmap'} estimation, time to "
                 f"error: {meta['scene_name']} "
                 f"({meta['width']}x{meta['height']}, {len(meta['views'])} views, "
                 f"max_bounces {meta['max_bounces']})", fontsize=11)
    ax.legend(fontsize=8, loc="upper center", bbox_to_anchor=(0.5, -0.11), ncol=1,
              frameon=False)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


# --------------------------------------------------------------------------

def parse_res(s: str) -> list[tuple[int, int]]:
    out = []
    for part in s.split(","):
        w, h = part.lower().split("x")
        out.append((int(w), int(h)))
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scene", type=Path, default=ms.DEFAULT_SCENE)
    ap.add_argument("--bin", type=Path, default=ms.DEFAULT_BIN, help="lightprobe binary")
    ap.add_argument("--out", type=Path, default=ms.REPO / "out" / "bench_estimate",
                    help="chart + JSON go here (default <repo>/out/bench_estimate, git-ignored)")
    ap.add_argument("--workdir", type=Path, default=None,
                    help="references and lightprobe outputs (default: a new temp dir)")
    ap.add_argument("--rings", type=int, default=9)
    ap.add_argument("--curve-spp", default="64,128,256",
                    help="extra lightprobe transport spp for the curve (the sidecar's is "
                         "always run)")
    ap.add_argument("--lp-repeat", type=int, default=1,
                    help="repetitions of the main lightprobe run (median times)")
    ap.add_argument("--big-rings", type=int, default=25, help="0 = skip the memory run")
    ap.add_argument("--spheres", type=int, default=2, metavar="K",
                    help="also run `estimate --model spheres:K` (--lp-repeat times, median "
                         "times) for the sphere-light model; 0 = skip")
    ap.add_argument("--mi-res", default="32x16", help="Mitsuba envmap WxH list, e.g. 32x16,64x32")
    ap.add_argument("--mi-steps", type=int, default=200)
    ap.add_argument("--mi-spp", type=int, default=16, help="spp per view and step")
    ap.add_argument("--mi-lr", type=float, default=0.3)
    ap.add_argument("--mi-loss", choices=("l1", "l2"), default="l2")
    ap.add_argument("--mi-init", default="match", help="'match' or a constant, e.g. 0.5")
    ap.add_argument("--mi-eval-every", type=int, default=10)
    ap.add_argument("--mi-eval-spp", type=int, default=None, help="default: the sidecar's")
    ap.add_argument("--mi-integrator", default="prb")
    ap.add_argument("--no-crosscheck", dest="crosscheck", action="store_false")
    ap.add_argument("--wait-idle", type=float, default=0.0, metavar="SECONDS",
                    help="before each timed run (every lightprobe process, each Mitsuba "
                         "optimisation) wait up to this long for other processes to use < 0.2 "
                         "cores (a concurrent build skews timings); what they used during each "
                         "run is recorded either way")
    ap.add_argument("--replot", type=Path, default=None,
                    help="only redraw the chart from a bench_estimate.json (into --out)")
    ap.add_argument("--quick", action="store_true",
                    help="smoke test: 30 Mitsuba steps, no curve/big runs, one run each "
                         "of the main lightprobe and the sphere model")
    args = ap.parse_args()
    if args.replot:
        j = json.loads(args.replot.read_text())
        args.out.mkdir(parents=True, exist_ok=True)
        png = args.out / "estimate_vs_mitsuba.png"
        j["time_to_error"] = time_to_error(j["lightprobe"], j["mitsuba"])   # pure: recomputed
        j["time_to_error_same_evaluator"] = time_to_error(j["lightprobe"], j["mitsuba"],
                                                          "rel_mae_by_mitsuba")
        sp = j.get("spheres")                     # absent in files from before --spheres
        if sp:
            sp["vs_mitsuba"] = sphere_vs_mitsuba(sp, j["mitsuba"])
        chart(png, j["lightprobe"], j["mitsuba"], j["time_to_error"], j["meta"], sp)
        (args.out / "bench_estimate.json").write_text(json.dumps(j, indent=2, default=float) + "\n")
        log(f"wrote {png} and {args.out / 'bench_estimate.json'}")
        return 0
    if args.quick:
        args.mi_steps, args.curve_spp, args.big_rings, args.lp_repeat = 30, "", 0, 1
    args.curve_spp = [int(s) for s in args.curve_spp.split(",") if s.strip()]
    t_start = time.time()
    work = args.workdir or Path(tempfile.mkdtemp(prefix="bench_estimate_"))
    work.mkdir(parents=True, exist_ok=True)
    args.out.mkdir(parents=True, exist_ok=True)
    loads = [load()]
    log(f"workdir {work}; out {args.out}; {os.cpu_count()} CPUs; load average {loads[0]}")

    variant = ms.set_variant(require_llvm=True)
    import drjit as dr
    import mitsuba as mi
    desc = ms.described_scene(args.scene, args.bin)
    st = desc["settings"]
    views = [c["name"] for c in desc["cameras"]]
    binary = binary_provenance(args.bin)
    log(f"lightprobe binary {binary['path']} built {binary['mtime']} sha256 "
        f"{binary['sha256'][:12]}; repo HEAD {binary['git_head']}")

    # 1. references, once
    ref = work / "reference"
    rr = run_timed([args.bin, "render-reference", args.scene, "--out", ref, "--quiet", "--json"])
    ref_json = json.loads(rr["stdout"])
    refs = {v: read_rgba(ref / f"{v}.exr") for v in views}
    log(f"references: {views} {st['width']}x{st['height']} {ref_json['settings']['spp']} spp "
        f"seed {ref_json['settings']['seed']} max_bounces {st['max_bounces']} "
        f"({rr['wall_seconds']:.1f} s) -> {ref}")

    # 2. lightprobe
    idle = {}
    log(f"lightprobe estimate (load {load()}):")
    lp = run_lightprobe_suite(args, ref, work)
    loads += [lp["load_before"], lp["load_after"]]
    sp = None
    if args.spheres:
        log(f"lightprobe estimate --model spheres:{args.spheres} (load {load()}):")
        sp = run_sphere_suite(args, ref, work)
        loads += [sp["load_before"], sp["load_after"]]
    binary_after = binary_provenance(args.bin)

    # 3. Mitsuba
    meshes = ms.load_meshes(ms.sidecar_gltf(args.scene))
    mitsuba = []
    for (w, h) in parse_res(args.mi_res):
        log(f"Mitsuba {mi.__version__} {variant}: {w}x{h} envmap, {args.mi_integrator}, "
            f"{args.mi_steps} steps x {args.mi_spp} spp/view, Adam lr {args.mi_lr}, "
            f"{args.mi_loss.upper()} loss, init {args.mi_init} (load {load()}):")
        l0 = load()
        fit = MitsubaFit(args, desc, meshes, refs, w, h)
        if args.wait_idle:
            idle[f"mitsuba_{w}x{h}"] = wi = wait_idle(args.wait_idle)
            log(f"  waited {wi['waited_seconds']:.0f} s for an idle machine: other processes "
                f"at {wi['other_cores_last_window']:.2f} cores")
        with CpuMonitor() as cm:
            r = fit.run()
        r["cpu"] = cm.result
        r["load_before"], r["load_after"] = l0, load()
        loads += [l0, r["load_after"]]
        mitsuba.append(r)
        log(f"  -> best relMAE {r['best']['rel_mae']:.4f} at step {r['best']['step']} "
            f"({r['best']['seconds']:.1f} s), final {r['final']['rel_mae']:.4f}; scene build "
            f"{r['scene_build_seconds']:.1f} s, first step {r['first_step_seconds']:.2f} s, "
            f"median step {r['median_step_seconds']:.3f} s; other processes used "
            f"{r['cpu']['other_cores']:.2f} cores meanwhile")
    mi_rss = __import__("resource").getrusage(__import__("resource").RUSAGE_SELF).ru_maxrss * 1024

    cc = None
    if args.crosscheck:      # every lightprobe envmap run of the time-to-error
        cc = crosscheck_all(args, desc, meshes, refs, lp)

    # 4. time-to-error and goals
    tte = time_to_error(lp, mitsuba)
    tte_same = time_to_error(lp, mitsuba, "rel_mae_by_mitsuba") if cc else None
    mn = lp["main"]

    def speed_goal(t: dict, key: str) -> dict:
        head = t["per_resolution"][0]
        return {
            "lightprobe_error": key, "lightprobe_rel_mae": mn[key],
            "ratio_fit": head.get("ratio_fit"),
            "ratio_process_wall": head.get("ratio_process_wall"),
            "lightprobe_error_le_mitsuba_best": mn[key] <= min(m["best"]["rel_mae"]
                                                               for m in mitsuba),
            "met": bool(head.get("ratio_fit") and head["ratio_fit"] >= 20),
            "met_by_process_wall": bool(head.get("ratio_process_wall")
                                        and head["ratio_process_wall"] >= 20),
        }

    goals = {
        "speed_20x_at_equal_or_lower_error": {
            **speed_goal(tte, "rel_mae"),
            "same_evaluator": speed_goal(tte_same, "rel_mae_by_mitsuba") if tte_same else None,
        },
        "under_5s_wall": {"process_wall_seconds": mn["process_wall_seconds"],
                          "process_wall_excl_evaluation_seconds":
                              mn["process_wall_excl_evaluation_seconds"],
                          "fit_seconds": mn["fit_seconds"],
                          "met_by_process_wall": mn["process_wall_seconds"] < 5,
                          "met_excl_evaluation": mn["process_wall_excl_evaluation_seconds"] < 5},
    }
    if sp:
        sp["vs_mitsuba"] = sphere_vs_mitsuba(sp, mitsuba)
        goals["spheres_under_15s"] = {"model": sp["model"], "model_seconds": sp["model_seconds"],
                                      "rel_mae": sp["rel_mae"], "met": sp["goal_under_15_s_met"]}
    if lp.get("big"):
        b = lp["big"]
        goals["peak_memory_25_rings_under_1GiB"] = {
            "rings": b["rings"], "peak_bytes": b["peak_bytes"], "max_rss_bytes": b["max_rss_bytes"],
            "met": max(b["peak_bytes"], b["max_rss_bytes"]) < GIB}
    flat = [x for l3 in loads for x in l3[:1]]
    meta = {"scene_name": Path(args.scene).stem, "width": st["width"], "height": st["height"],
            "views": views, "max_bounces": st["max_bounces"], "cpus": os.cpu_count(),
            "load_summary": f"1-min {min(flat):.2f}-{max(flat):.2f}; other processes used "
                            f"{mn['cpu']['other_cores']:.2f} cores during lightprobe's main run, "
                            + ", ".join(f"{m['cpu']['other_cores']:.2f}" for m in mitsuba)
                            + " during Mitsuba's"
                            + ("; " + ", ".join(f"{r['cpu']['other_cores']:.2f}"
                                                for r in sp["runs"])
                               + " during the sphere runs" if sp else "")}
    png = args.out / "estimate_vs_mitsuba.png"
    chart(png, lp, mitsuba, tte, meta, sp)

    result = {
        "scene": str(args.scene), "views": views, "settings": st, "cpus": os.cpu_count(),
        "loadavg_samples": loads, "wait_idle": idle, "lightprobe_binary": binary,
        "lightprobe_binary_after_lightprobe_runs": binary_after, "reference": {"dir": str(ref), "seconds": rr["wall_seconds"]},
        "lightprobe": lp, "spheres": sp, "mitsuba": mitsuba, "mitsuba_version": mi.__version__,
        "mitsuba_variant": variant, "mitsuba_threads": dr.thread_count(),
        "mitsuba_python_max_rss_bytes": mi_rss, "crosscheck": cc, "time_to_error": tte,
        "time_to_error_same_evaluator": tte_same, "goals": goals, "meta": meta, "chart": str(png), "seconds": time.time() - t_start,
        "args": {k: (str(v) if isinstance(v, Path) else v) for k, v in vars(args).items()},
    }
    jpath = args.out / "bench_estimate.json"
    jpath.write_text(json.dumps(result, indent=2, default=float) + "\n")

    # 5. summary
    log("\n=== summary ===")
    log(f"lightprobe {args.rings} rings ({mn['cells']} cells), solver {mn['solver']}, rounds "
        f"{mn['rounds']}, {mn['threads']} threads:")
    if binary_after["sha256"] != binary["sha256"]:
        log(f"  WARNING: the lightprobe binary was rebuilt during the lightprobe runs "
            f"({binary_after['mtime']}): they may not all be of the same build")
    for r in lp["curve"]:
        by_mi = r.get("rel_mae_by_mitsuba")
        log(f"  spp {r['transport_spp']:4d}: relMAE {r['rel_mae']:.4f}"
            + (f" (by Mitsuba {by_mi:.4f})" if by_mi is not None else "")
            + f"  fit {r['fit_seconds']:.2f} s"
            f"  report total {r['total_seconds']:.2f} s  process wall "
            f"{r['process_wall_seconds']:.2f} s (excl. evaluation "
            f"{r['process_wall_excl_evaluation_seconds']:.2f} s)")
    log(f"  noise floor relMAE {mn['noise_floor_rel_mae']:.4f}")
    if lp.get("big"):
        b = lp["big"]
        log(f"  {b['rings']} rings: relMAE {b['rel_mae']:.4f}, fit {b['fit_seconds']:.2f} s, peak "
            f"memory {b['peak_bytes'] / 2**20:.0f} MiB (max RSS {b['max_rss_bytes'] / 2**20:.0f} MiB)")
    for m in mitsuba:
        w, h = m["resolution"]
        pts = ", ".join(f"{c['seconds']:.1f}s:{c['rel_mae']:.4f}" for c in m["curve"])
        log(f"Mitsuba {w}x{h}: best {m['best']['rel_mae']:.4f} (step {m['best']['step']}, "
            f"{m['best']['seconds']:.1f} s), final {m['final']['rel_mae']:.4f}; curve {pts}")
    def log_tte(t: dict, label: str = "") -> None:
        for row, m in zip(t["per_resolution"], mitsuba):
            w, h = row["resolution"]
            if row.get("mitsuba_seconds") and row.get("lightprobe_fit_seconds"):
                log(f"{label}time to relMAE {row['target_rel_mae']:.4f} ({row['target_is']}), "
                    f"Mitsuba {w}x{h}: Mitsuba {row['mitsuba_seconds']:.1f} s (previous "
                    f"checkpoint {row['mitsuba_seconds_previous_checkpoint']:.1f} s; "
                    f"+{m['scene_build_seconds']:.1f} s scene build), lightprobe fit "
                    f"{row['lightprobe_fit_seconds']:.2f} s (spp "
                    f"{row['lightprobe_transport_spp']}) / process wall "
                    f"{row['lightprobe_process_wall_seconds']:.2f} s -> ratio "
                    f"{row['ratio_fit']:.1f}x (fit), {row['ratio_process_wall']:.1f}x (process "
                    f"wall), {row['ratio_process_wall_excl_evaluation']:.1f}x (wall excl. "
                    f"evaluation)")
            elif not row.get("mitsuba_seconds"):
                log(f"{label}time to relMAE {row['target_rel_mae']:.4f} ({row['target_is']}), "
                    f"Mitsuba {w}x{h}: Mitsuba never reaches it")
        for row in t["per_resolution"]:
            w, h = row["resolution"]
            pts = [f"{q['rel_mae']:.4f}: lightprobe {q['lightprobe_fit_seconds']:.2f} s (spp "
                   f"{q['transport_spp']}) vs Mitsuba {q['mitsuba_seconds']:.1f} s = "
                   f"{q['ratio_fit']:.1f}x" if q["mitsuba_seconds"] else
                   f"{q['rel_mae']:.4f}: Mitsuba {w}x{h} never reaches it"
                   for q in row["per_lightprobe_point"]]
            log(f"{label}Mitsuba {w}x{h} time to each lightprobe point's error: "
                + "; ".join(pts))

    log_tte(tte)
    if tte_same:
        log_tte(tte_same, "same evaluator (Mitsuba renders both maps): ")
    else:
        log("same evaluator (Mitsuba renders both maps): not run (--no-crosscheck)")
    if sp:
        vs = sp["vs_mitsuba"]
        log(f"sphere model ({sp['model']}): relMAE {100 * sp['rel_mae']:.2f}% (noise floor "
            f"{100 * sp['noise_floor_rel_mae']:.2f}%, envmap {100 * sp['envmap_rel_mae']:.2f}%) in "
            f"{sp['model_seconds']:.1f} s (envmap init {sp['envmap_fit_seconds']:.1f} s + spheres "
            f"{sp['sphere_fit_seconds']:.1f} s; median of {sp['repeats']}); Mitsuba best "
            f"{100 * vs['mitsuba_best_rel_mae']:.2f}% after {vs['mitsuba_plateau_seconds']:.1f} s "
            f"to plateau; goal < 15 s: {'met' if sp['goal_under_15_s_met'] else 'NOT met'}")
        log(f"  process wall {sp['process_wall_seconds']:.1f} s (excl. evaluation "
            f"{sp['process_wall_excl_evaluation_seconds']:.1f} s), {sp['renders']} renders, "
            f"{sp['iterations']} iterations; fitted lights: "
            + ", ".join(str(fl.get("status")) for fl in sp["lights"] or []))
        num = lambda v, f: "?" if v is None else format(v, f)  # noqa: E731
        for i, rc in enumerate(sp["recovery"] or []):
            if rc.get("centre_error_m") is None:
                log(f"  true light {i}: not recovered (the model has fewer lights)")
                continue
            frac = rc.get("centre_error_fraction_of_distance")
            log(f"  true light {i} ({rc['true_distance_m']:.2f} m from the scene centre): centre "
                f"off {rc['centre_error_m']:.3f} m "
                f"({num(frac and 100 * frac, '.1f')}%"
                f" of its distance), radius {num(rc.get('radius'), '.3f')} (true "
                f"{rc['true_radius']:.3f}), power x{num(rc.get('power_ratio'), '.3f')}")
        log(f"  Mitsuba's best {vs['mitsuba_best_rel_mae']:.4f} ({vs['mitsuba_best_resolution'][0]}x"
            f"{vs['mitsuba_best_resolution'][1]}, {vs['mitsuba_best_seconds']:.1f} s); first within "
            f"{100 * vs['plateau_tolerance_relative']:.0f}% of it at {vs['mitsuba_plateau_seconds']:.1f} s "
            f"({vs['mitsuba_plateau_rel_mae']:.4f}, {vs['mitsuba_plateau_resolution'][0]}x"
            f"{vs['mitsuba_plateau_resolution'][1]})"
            + ("; its best is its last checkpoint: still improving, the plateau is where it "
               "stopped" if vs["mitsuba_best_at_last_checkpoint"] else "")
            + "; Mitsuba to the sphere model's error: "
            + ", ".join(f"{r['resolution'][0]}x{r['resolution'][1]} "
                        + (f"{r['seconds_to_sphere_error']:.1f} s" if r["seconds_to_sphere_error"]
                           is not None else "never")
                        for r in vs["per_resolution"]))
    def verdict(g: dict) -> str:
        return (f"{'MET' if g['met'] else 'NOT MET'} (fit ratio "
                f"{g['ratio_fit'] and round(g['ratio_fit'], 1)}, process-wall ratio "
                f"{g['ratio_process_wall'] and round(g['ratio_process_wall'], 1)}; lightprobe "
                f"error {g['lightprobe_rel_mae']:.4f} "
                f"{'<=' if g['lightprobe_error_le_mitsuba_best'] else '>'} Mitsuba's best)")

    g = goals["speed_20x_at_equal_or_lower_error"]
    log(f"GOAL >= 20x faster at equal or lower error: by own re-renders {verdict(g)}; "
        f"same evaluator (Mitsuba renders both maps) "
        + (verdict(g["same_evaluator"]) if g["same_evaluator"] else "not run (--no-crosscheck)"))
    g = goals["under_5s_wall"]
    log(f"GOAL under 5 s wall: process wall {g['process_wall_seconds']:.2f} s -> "
        f"{'MET' if g['met_by_process_wall'] else 'NOT MET'}; excluding its evaluation renders "
        f"{g['process_wall_excl_evaluation_seconds']:.2f} s -> "
        f"{'MET' if g['met_excl_evaluation'] else 'NOT MET'}; fit {g['fit_seconds']:.2f} s")
    if "spheres_under_15s" in goals:
        g = goals["spheres_under_15s"]
        log(f"GOAL sphere model ({g['model']}) under 15 s: envmap fit + sphere fit "
            f"{g['model_seconds']:.2f} s -> {'MET' if g['met'] else 'NOT MET'}")
    if "peak_memory_25_rings_under_1GiB" in goals:
        g = goals["peak_memory_25_rings_under_1GiB"]
        log(f"GOAL peak memory at {g['rings']} rings < 1 GiB: {g['peak_bytes'] / 2**20:.0f} MiB "
            f"(max RSS {g['max_rss_bytes'] / 2**20:.0f} MiB) -> {'MET' if g['met'] else 'NOT MET'}")
    log(f"load average samples (1-min): {flat} on {os.cpu_count()} CPUs; {meta['load_summary']}")
    log(f"wrote {png} and {jpath} ({time.time() - t_start:.0f} s)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
