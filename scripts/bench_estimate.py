#!/usr/bin/env python3
"""Envmap estimation, lightprobe against Mitsuba 3, compared like with like.

Both tools estimate the environment lighting that explains the same reference
images (default: the bundled tabletop, 2 views at 128x96, lit by the sidecar's
two sphere lights, 512 spp, max_bounces 2). The error of an estimate is
relMAE = sum|x - r| / sum|r| over the references' geometry mask (alpha > 0),
RGB, averaged over the views, of a fresh render of the estimated lighting.

The protocol, and what keeps it fair:

* References rendered by each tool in turn (--references lightprobe,mitsuba):
  the whole comparison runs once per reference set, so neither tool is scored
  only on images its own renderer made.
* lightprobe: `estimate --reference REFS --rings R` for R in --rings-list
  (its map sizes), at the sidecar's transport spp; at --rings (9, the default
  map) also --curve-spp for its time/error curve, and --lp-repeat runs (median
  times).
* Mitsuba (llvm_ad_rgb): an `envmap` emitter's W x H lat-long bitmap, for each
  size in --mi-res, optimised by Adam through the `prb` integrator (latent
  tensor padded into `envmap.data`; init a constant matching the references'
  mean colour, timed; relMAE-normalised L2 loss; clamp >= 0), run to
  convergence: it stops when the mean error of its checkpoints over the last
  --mi-patience steps is less than --mi-min-gain (relative) below that of the
  --mi-patience steps before (each fit with its own evaluation seeds), or at the
  --mi-steps budget (then it is reported as not converged and no verdict can
  be met). Its whole curve is kept: every --mi-eval-every steps the current
  map is rendered with the `path` integrator at the sidecar's spp.
* One evaluator for both maps, each tool in turn: every final map (each
  lightprobe ring count; each Mitsuba size's best checkpoint) is rendered by
  Mitsuba and by lightprobe at --score-spp with fresh seeds and scored against
  the same references. lightprobe renders a Mitsuba map exactly as Mitsuba
  interprets it (bilinear between texels at u = (j+0.5)/W, theta = i pi/(H-1)),
  sampled on a fine lat-long grid and averaged into 128 rings (cells of 1.4 deg
  against texels of 5.6 deg and more).
* Time to equal error, the same evaluator for both curves: Mitsuba's
  checkpoints (its renders at the sidecar's spp) against every lightprobe run's
  map rendered by Mitsuba the same way. Two clocks, each excluding the same
  things for both tools:
    fit      lightprobe timings.fit_seconds (transport + solve, after scene
             load and BVH build); Mitsuba's optimisation time (its init render
             and every step, JIT included, after scene build). Both exclude
             evaluation renders.
    process  lightprobe's whole process wall minus its own evaluation renders
             (noise floor, re-render), misfit diagnosis and oracle; Mitsuba's
             import + variant set-up + scene build and loss set-up +
             optimisation (the Python process's equivalent; its glTF parsing,
             done by this script, is left out).
  Mitsuba's time is its first checkpoint at or below the error, so up to
  --mi-eval-every steps late; the previous checkpoint is kept as its bound.
* The verdict "lightprobe >= 20x faster at equal or lower error" is met for a
  lightprobe map only when every half holds: the speed ratio on the clock is
  >= 20 (Mitsuba never reaching the error counts as infinitely slower); the
  map's error is <= Mitsuba's best map's under both evaluators; and every
  Mitsuba fit converged. It is given for the default map (--rings) and for
  lightprobe's most accurate map by its own report, on both clocks, per
  reference set. When Mitsuba never reaches the error, ratio_*_at_least
  gives its longest converged run over lightprobe's time.
  `--test-verdict` checks this logic on constructed cases (run by CI). In the
  JSON a ratio of null means Mitsuba never reached the error.
* Also: maps at comparable parameter counts (cells against texels), each
  tool's best, the peak memory at 25 rings, and the sphere-light model
  (--spheres K: `estimate --model spheres:K`, on lightprobe's references).

Writes OUT/estimate_vs_mitsuba.{png,svg} (error against time on the fit
clock, and error against parameter count under both evaluators) and
OUT/bench_estimate.json (every number, the build measured, how many cores
other processes used during each timed run). On an idle 2-core machine the
defaults take about 30 minutes.

Usage: .venv/bin/python scripts/bench_estimate.py [--out DIR]
       [--references lightprobe,mitsuba] [--rings-list 5,9,13,17,21,25,41]
       [--mi-res 16x8,32x16,64x32] [--mi-steps 1500] [--mi-patience 200]
       [--mi-min-gain 0.005] [--score-spp 2048] [--spheres 2] [--quick]
       --replot OUT/bench_estimate.json --out OUT   (redraw the chart only)
       --test-verdict                               (check the verdict logic)
"""

from __future__ import annotations

import argparse
import json
import math
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
from figure_check import assert_text_apart  # noqa: E402

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
    """Every map size of --rings-list at the sidecar's spp (the main ring count --lp-repeat
    times, median times), and the main ring count at each --curve-spp."""
    res = {"load_before": load(), "maps": [], "curve": []}
    for rings in args.rings_list:
        runs = []
        for k in range(args.lp_repeat if rings == args.rings else 1):
            runs.append(lp_estimate(args.bin, args.scene, ref, work / f"lp_r{rings}_{k}", rings,
                                    None, args.wait_idle))
        r = dict(runs[0])
        for key in ("fit_seconds", "total_seconds", "process_wall_seconds",
                    "process_wall_excl_evaluation_seconds"):
            r[key] = statistics.median(x[key] for x in runs)
            r[key + "_runs"] = [x[key] for x in runs]
        res["maps"].append(r)
        log(f"  lightprobe {rings} rings ({r['cells']} cells), spp {r['transport_spp']}"
            f"{f' ({len(runs)} runs, median)' if len(runs) > 1 else ''}: relMAE "
            f"{r['rel_mae']:.4f}, fit {r['fit_seconds']:.2f} s, process wall "
            f"{r['process_wall_seconds']:.2f} s (excl. evaluation "
            f"{r['process_wall_excl_evaluation_seconds']:.2f} s), peak "
            f"{r['peak_bytes'] / 2**20:.0f} MiB; other processes {r['cpu']['other_cores']:.2f} "
            "cores")
    main = next(r for r in res["maps"] if r["rings"] == args.rings)
    for spp in args.curve_spp:
        if spp == main["transport_spp"]:
            continue
        r = lp_estimate(args.bin, args.scene, ref, work / f"lp_r{args.rings}_spp{spp}",
                        args.rings, spp, args.wait_idle)
        res["curve"].append(r)
        log(f"  lightprobe {args.rings} rings, spp {spp}: relMAE {r['rel_mae']:.4f}, fit "
            f"{r['fit_seconds']:.2f} s; other processes {r['cpu']['other_cores']:.2f} cores")
    res["curve"] = sorted(res["curve"] + [main], key=lambda r: r["transport_spp"])
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
# references, Mitsuba's fit, the two evaluators
# --------------------------------------------------------------------------

def read_rgba(path: Path) -> np.ndarray:
    import mitsuba as mi
    a = np.array(mi.Bitmap(str(path)), dtype=np.float32)
    assert a.ndim == 3 and a.shape[2] == 4, (path, a.shape)
    return a


def write_exr(path: Path, a: np.ndarray) -> None:
    import mitsuba as mi
    fmt = mi.Bitmap.PixelFormat.RGBA if a.shape[2] == 4 else mi.Bitmap.PixelFormat.RGB
    mi.Bitmap(np.ascontiguousarray(a, dtype=np.float32), fmt).write(str(path))


def rel_mae(img: np.ndarray, ref: np.ndarray, mask: np.ndarray) -> float:
    return float(np.abs(img[mask][:, :3] - ref[mask][:, :3]).sum()
                 / np.abs(ref[mask][:, :3]).sum())


def render_references(args, desc: dict, meshes, renderer: str, out: Path) -> dict:
    """The sidecar's lights rendered by `renderer` at the sidecar's spp into out/<view>.exr."""
    st = desc["settings"]
    t0 = time.perf_counter()
    if renderer == "lightprobe":
        run_timed([args.bin, "render-reference", args.scene, "--out", out, "--quiet"])
    else:
        import mitsuba as mi
        out.mkdir(parents=True, exist_ok=True)
        S = ms.build_scene(args.scene, args.bin, desc=desc, meshes=meshes)
        for i, c in enumerate(desc["cameras"]):
            img = np.array(mi.render(S.scene, sensor=S.sensors[c["name"]], seed=500_000 + i),
                           dtype=np.float32)
            write_exr(out / f"{c['name']}.exr", img)
    return {"renderer": renderer, "dir": str(out), "spp": st["spp"],
            "seconds": time.perf_counter() - t0}


class MitsubaFit:
    """Envmap optimisation in Mitsuba, to convergence; see the module docstring."""

    def __init__(self, args, desc, meshes, refs: dict, width: int, height: int, index: int):
        import drjit as dr
        import mitsuba as mi
        self.dr, self.mi = dr, mi
        self.args, self.refs, self.W, self.H = args, refs, width, height
        self.seed0 = 1_000_000 + 100_000 * index      # evaluation seeds of this fit alone
        self.views = list(refs)
        self.masks = {v: refs[v][..., 3] > 0 for v in self.views}
        st = desc["settings"]
        self.eval_spp = st["spp"]
        self.max_depth = st["max_bounces"] + 1
        t0 = time.perf_counter()
        self.S = ms.build_scene(args.scene, args.bin, desc=desc, meshes=meshes,
                                envmap=np.ones((height, width, 3), np.float32),
                                sphere_lights=False, spp=args.mi_spp)
        self.path = self.S.scene.integrator()          # validated against lightprobe
        self.prb = mi.load_dict({"type": "prb", "max_depth": self.max_depth,
                                 "rr_depth": self.max_depth + 100, "hide_emitters": True})
        self.params = mi.traverse(self.S.scene)
        self.key = "envmap.data"
        shape = tuple(self.params[self.key].shape)
        if shape != (height, width + 2, 3):
            raise SystemExit(f"unexpected {self.key} shape {shape} (Mitsuba version?)")
        cols = np.concatenate([[width - 1], np.arange(width), [0]])
        idx = (np.arange(height)[:, None, None] * width * 3 + cols[None, :, None] * 3
               + np.arange(3)[None, None, :]).ravel().astype(np.uint32)
        self.pad_index = mi.UInt32(idx)
        self.w = {}          # per view: reference, relMAE-normalised L2 weights
        for v in self.views:
            r = refs[v]
            m = np.repeat(self.masks[v][..., None], 4, -1)
            m[..., 3] = False
            mean = float(r[m].mean())
            self.w[v] = (mi.Float(r.ravel()),
                         mi.Float((m / (m.sum() * mean * mean)).astype(np.float32).ravel()))
        self.build_seconds = time.perf_counter() - t0
        # the emitter must keep the padded bitmap as given (its wrap columns included)
        probe = mi.TensorXf(np.random.default_rng(0).random((height, width, 3), np.float32))
        self.set_envmap(probe)
        if not np.allclose(np.array(self.params[self.key]), np.array(self.pad(probe))):
            raise SystemExit(f"{self.key} changed on update: the padding assumed here is wrong")
        # back to the unit map the initial constant is measured under
        self.set_envmap(mi.TensorXf(np.ones((height, width, 3), np.float32)))

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
                                         seed=self.seed0 + 2 * k + i), dtype=np.float32)
                per_view[v] = rel_mae(img, self.refs[v], self.masks[v])
        return {"rel_mae": float(np.mean(list(per_view.values()))), "views": per_view}

    def run(self) -> dict:
        mi, dr, a = self.mi, self.dr, self.args
        t0 = time.perf_counter()
        # init: a constant matching the references' mean colour, from one 32-spp render
        # under a unit envmap (timed: it is part of Mitsuba's method)
        ratios = []
        for i, v in enumerate(self.views):
            img = np.array(mi.render(self.S.scene, sensor=self.S.sensors[v],
                                     integrator=self.path, spp=32, seed=999_000 + i))
            m = self.masks[v]
            ratios.append(self.refs[v][m][:, :3].mean(0) / np.maximum(img[m][:, :3].mean(0), 1e-8))
        c = np.mean(ratios, 0).astype(np.float32)
        opt = mi.ad.Adam(lr=a.mi_lr)
        opt["x"] = mi.TensorXf(np.ascontiguousarray(np.broadcast_to(c, (self.H, self.W, 3))))
        clock = time.perf_counter() - t0
        curve, best_map, stop = [], None, "budget"

        def checkpoint(step: int) -> None:
            nonlocal best_map
            t = time.perf_counter()
            e = self.evaluate(opt["x"], len(curve))
            if not curve or e["rel_mae"] < min(p["rel_mae"] for p in curve):
                best_map = np.array(opt["x"], dtype=np.float32)
            curve.append({"step": step, "seconds": clock,
                          "eval_seconds": time.perf_counter() - t, **e})

        def converged(step: int) -> bool:
            """The mean error of the checkpoints in the last mi_patience steps is less than
            mi_min_gain (relative) below that of the mi_patience steps before (means: one
            checkpoint's evaluation noise is about the size of the gain)."""
            if step < 2 * a.mi_patience:
                return False
            now = [p["rel_mae"] for p in curve if p["step"] > step - a.mi_patience]
            before = [p["rel_mae"] for p in curve
                      if step - 2 * a.mi_patience < p["step"] <= step - a.mi_patience]
            return statistics.mean(before) - statistics.mean(now) < (
                a.mi_min_gain * statistics.mean(before))

        checkpoint(0)
        step_seconds = []
        for it in range(1, a.mi_steps + 1):
            t = time.perf_counter()
            self.set_envmap(opt["x"])
            loss = mi.Float(0.0)
            for i, v in enumerate(self.views):
                s = 4 * it + 2 * i
                img = mi.render(self.S.scene, self.params, sensor=self.S.sensors[v],
                                integrator=self.prb, spp=a.mi_spp, seed=s, seed_grad=s + 1)
                ref, w2 = self.w[v]
                d = img.array - ref
                loss = loss + dr.sum(w2 * d * d) / len(self.views)
            dr.backward(loss)
            opt.step()
            opt["x"] = dr.maximum(opt["x"], 0.0)
            dr.eval(opt["x"])
            dr.sync_thread()
            dt = time.perf_counter() - t
            step_seconds.append(dt)
            clock += dt
            if it % a.mi_eval_every == 0 or it == a.mi_steps:
                checkpoint(it)
                if it % (10 * a.mi_eval_every) == 0:
                    log(f"    step {it:5d}  opt time {clock:7.1f} s  relMAE "
                        f"{curve[-1]['rel_mae']:.4f}  best {min(p['rel_mae'] for p in curve):.4f}")
                if converged(it):
                    stop = "converged"
                    break
        best = min(curve, key=lambda p: p["rel_mae"])
        return {
            "resolution": [self.W, self.H], "parameters": 3 * self.W * self.H,
            "integrator": "prb", "eval_integrator": "path", "max_depth": self.max_depth,
            "spp_per_step": a.mi_spp, "eval_spp": self.eval_spp, "lr": a.mi_lr, "loss": "l2",
            "init_constant": c.tolist(), "steps_budget": a.mi_steps,
            "patience_steps": a.mi_patience, "min_gain": a.mi_min_gain,
            "steps": curve[-1]["step"], "stopped": stop, "converged": stop == "converged",
            "scene_build_seconds": self.build_seconds,
            "first_step_seconds": step_seconds[0] if step_seconds else None,
            "median_step_seconds": statistics.median(step_seconds) if step_seconds else None,
            "optimisation_seconds": clock, "curve": curve,
            "best": {k: best[k] for k in ("step", "seconds", "rel_mae")},
            "final": {k: curve[-1][k] for k in ("step", "seconds", "rel_mae")},
            "best_map": best_map,
        }


def mitsuba_map_on_fine_grid(x: np.ndarray, width: int = 1024) -> np.ndarray:
    """Mitsuba's envmap as Mitsuba evaluates it -- bilinear between texels at
    u = (j+0.5)/W (wrapping) and theta = i pi/(H-1) -- sampled at the texel positions
    of a finer map in the same convention (rows width/2 + 1)."""
    H, W, _ = x.shape
    h2 = width // 2 + 1
    r = np.arange(h2) / (h2 - 1) * (H - 1)
    r0 = np.minimum(np.floor(r).astype(int), H - 2)
    fr = (r - r0)[:, None, None]
    c = (np.arange(width) + 0.5) / width * W - 0.5
    c0 = np.floor(c).astype(int)
    fc = (c - c0)[None, :, None]
    c0, c1 = c0 % W, (c0 + 1) % W
    rows = x[r0] * (1 - fr) + x[r0 + 1] * fr
    return (rows[:, c0] * (1 - fc) + rows[:, c1] * fc).astype(np.float32)


def score_by_mitsuba(args, desc, meshes, refs: dict, envmap, spp: int, seed0: int) -> dict:
    """relMAE of Mitsuba's `path` render of a lat-long map (path or array, Mitsuba's
    convention) against the references."""
    import mitsuba as mi
    S = ms.build_scene(args.scene, args.bin, desc=desc, meshes=meshes, envmap=envmap,
                       sphere_lights=False, spp=spp)
    views = {}
    for i, v in enumerate(refs):
        img = np.array(mi.render(S.scene, sensor=S.sensors[v], seed=seed0 + i), dtype=np.float32)
        views[v] = rel_mae(img, refs[v], refs[v][..., 3] > 0)
    return {"rel_mae": float(np.mean(list(views.values()))), "views": views, "spp": spp}


def score_by_lightprobe(args, refs: dict, envmap: Path, spp: int, seed: int, out: Path,
                        latlong: bool) -> dict:
    """relMAE of lightprobe's render of a ring envmap (envmap.ron) or of a lat-long EXR in
    Mitsuba's convention (averaged into 128 rings) against the references."""
    cmd = [args.bin, "render-reference", args.scene, "--envmap", envmap, "--no-sphere-lights",
           "--spp", spp, "--seed", seed, "--out", out, "--quiet"]
    if latlong:
        cmd += ["--envmap-target", "mitsuba", "--envmap-rings", 128]
    run_timed(cmd)
    views = {v: rel_mae(read_rgba(out / f"{v}.exr"), refs[v], refs[v][..., 3] > 0)
             for v in refs}
    return {"rel_mae": float(np.mean(list(views.values()))), "views": views, "spp": spp}


# --------------------------------------------------------------------------
# time to error and the verdict (pure: recomputed by --replot)
# --------------------------------------------------------------------------

SPEED_FACTOR = 20.0             # the goal: lightprobe >= 20x faster at equal or lower error
MITSUBA_PLATEAU = 0.02          # "plateau": first checkpoint within 2% (relative) of the best
EVALUATORS = ("mitsuba", "lightprobe")


def first_at_or_below(points: list[tuple[float, float]], target: float):
    """(time, previous time) of the first (time, err) with err <= target, in time order."""
    prev = 0.0
    for t, e in sorted(points):
        if e <= target:
            return t, prev
        prev = t
    return None, None


def verdict(ratio: float | None, lp_errors: dict, mi_best_errors: dict, converged: bool,
            factor: float = SPEED_FACTOR) -> dict:
    """The goal for one lightprobe map on one clock. ratio: Mitsuba's time over
    lightprobe's to the map's error (math.inf when Mitsuba never reaches it, None when not
    measured); lp_errors / mi_best_errors: evaluator -> relMAE of the map and of Mitsuba's
    best map. Met only when the speed half, the error half under every evaluator, and
    Mitsuba's convergence all hold."""
    speed = ratio is not None and ratio >= factor
    error = (set(lp_errors) == set(mi_best_errors) == set(EVALUATORS)
             and all(lp_errors[e] <= mi_best_errors[e] for e in lp_errors))
    return {"speed_ratio": ratio, "speed_factor": factor, "speed_half": bool(speed),
            "error_half": bool(error), "mitsuba_converged": bool(converged),
            "met": bool(speed and error and converged)}


def test_verdict() -> None:
    """The cases a benchmark must not get wrong (run by CI: `--test-verdict`)."""
    good, worse = {"mitsuba": 0.090, "lightprobe": 0.091}, {"mitsuba": 0.095, "lightprobe": 0.094}
    cases = [
        ((67.0, worse, good, True), False, "fast but less accurate under both evaluators"),
        ((67.0, {"mitsuba": 0.096, "lightprobe": 0.090}, good, True), False,
         "less accurate under one evaluator"),
        ((10.0, good, worse, True), False, "more accurate but only 10x faster"),
        ((None, good, worse, True), False, "speed not measured"),
        ((67.0, good, worse, False), False, "Mitsuba stopped at its budget, still improving"),
        ((67.0, good, {"mitsuba": 0.095}, True), False, "an evaluator missing for Mitsuba"),
        ((67.0, {}, {}, True), False, "no errors at all"),
        ((67.0, {"mitsuba": 0.09}, {"mitsuba": 0.095}, True), False,
         "one evaluator only, for both tools"),
        ((20.0, good, good, True), True, "exactly 20x at equal error"),
        ((math.inf, good, worse, True), True, "Mitsuba never reaches the error"),
    ]
    for args, want, what in cases:
        got = verdict(*args)
        assert got["met"] is want, f"verdict wrong for {what}: {got}"
        assert got["met"] == (got["speed_half"] and got["error_half"]
                              and got["mitsuba_converged"]), got
    print(f"verdict logic: all {len(cases)} cases right")


def compare(lp: dict, fits: list[dict], mitsuba_import_seconds: float, main_rings: int) -> dict:
    """Time to equal error on both clocks (Mitsuba's renders at the sidecar's spp judging
    both curves), the verdicts, and the maps side by side."""
    converged = all(f["converged"] for f in fits)
    mi_best = {e: min(f["score"][e]["rel_mae"] for f in fits) for e in EVALUATORS}
    clocks = {
        "fit": (lambda r: r["fit_seconds"], lambda f, t: t),
        "process": (lambda r: r["process_wall_excl_evaluation_seconds"]
                    - r["timings"].get("diagnosis_seconds", 0.0)
                    - r["timings"].get("oracle_seconds", 0.0),
                    lambda f, t: mitsuba_import_seconds + f["scene_build_seconds"] + t),
    }

    def to_error(r: dict) -> dict:
        err = r["curve_eval"]["rel_mae"]
        row = {"rings": r["rings"], "cells": r["cells"], "transport_spp": r["transport_spp"],
               "rel_mae_by_mitsuba": err, "per_resolution": []}
        for f in fits:
            t, prev = first_at_or_below([(p["seconds"], p["rel_mae"]) for p in f["curve"]], err)
            row["per_resolution"].append({"resolution": f["resolution"], "fit_seconds": t,
                                          "fit_seconds_previous_checkpoint": prev})
        for clock, (lp_t, mi_t) in clocks.items():
            ts = [mi_t(f, q["fit_seconds"]) for f, q in zip(fits, row["per_resolution"])
                  if q["fit_seconds"] is not None]
            row[f"lightprobe_{clock}_seconds"] = lp_t(r)
            row[f"mitsuba_{clock}_seconds"] = min(ts) if ts else None
            row[f"ratio_{clock}"] = (min(ts) / lp_t(r)) if ts else math.inf
            # never reached: at least the longest converged run over lightprobe's time
            row[f"ratio_{clock}_at_least"] = (min(ts) if ts else max(
                mi_t(f, f["optimisation_seconds"]) for f in fits)) / lp_t(r)
        return row

    points = [to_error(r) for r in lp["curve"]] + [to_error(r) for r in lp["maps"]
                                                   if r not in lp["curve"]]
    default = next(r for r in lp["maps"] if r["rings"] == main_rings)
    # picked on lightprobe's own report, not on the scores it is then judged by
    best = min(lp["maps"], key=lambda r: r["rel_mae"])
    verdicts = {}
    for name, r in (("default_map", default), ("most_accurate_map", best)):
        row = to_error(r)
        errs = {e: r["score"][e]["rel_mae"] for e in EVALUATORS}
        verdicts[name] = {"rings": r["rings"], "cells": r["cells"], "rel_mae": errs,
                          "mitsuba_best_rel_mae": mi_best,
                          "ratio_at_least": {c: row[f"ratio_{c}_at_least"] for c in clocks},
                          **{clock: verdict(row[f"ratio_{clock}"], errs, mi_best, converged)
                             for clock in clocks}}
    sizes = []
    for f in fits:
        near = min(lp["maps"], key=lambda r: abs(math.log(3 * r["cells"] / f["parameters"])))
        sizes.append({
            "mitsuba_resolution": f["resolution"], "mitsuba_parameters": f["parameters"],
            "mitsuba_rel_mae": {e: f["score"][e]["rel_mae"] for e in EVALUATORS},
            "mitsuba_best_fit_seconds": f["best"]["seconds"], "mitsuba_converged": f["converged"],
            "lightprobe_rings": near["rings"], "lightprobe_parameters": 3 * near["cells"],
            "lightprobe_rel_mae": {e: near["score"][e]["rel_mae"] for e in EVALUATORS},
            "lightprobe_fit_seconds": near["fit_seconds"],
            "more_accurate": {e: "lightprobe" if near["score"][e]["rel_mae"]
                              <= f["score"][e]["rel_mae"] else "mitsuba" for e in EVALUATORS},
        })
    return {"clocks": {"fit": "lightprobe timings.fit_seconds; Mitsuba optimisation incl. "
                              "init render and JIT, excl. scene build and evaluations",
                       "process": "lightprobe process wall excl. its evaluation renders, "
                                  "misfit diagnosis and oracle (incl. process start, scene "
                                  "load, BVH, reading references, writing outputs); Mitsuba "
                                  "import + variant + scene build and loss set-up + "
                                  "optimisation (excl. Python start and the glTF parsing "
                                  "this script does for it)"},
            "mitsuba_converged": converged, "mitsuba_best_rel_mae": mi_best,
            "time_to_error": points, "verdicts": verdicts, "comparable_sizes": sizes}


def sphere_vs_mitsuba(sp: dict, fits: list[dict]) -> dict | None:
    """The sphere model beside Mitsuba's envmap fits: Mitsuba's best checkpoint, when it
    first came within MITSUBA_PLATEAU of it, and when (if ever) it reached the sphere
    model's error."""
    if not fits:
        return None
    best_f = min(fits, key=lambda f: f["best"]["rel_mae"])
    best = best_f["best"]["rel_mae"]
    t, e, f0 = min(((p["seconds"], p["rel_mae"], f) for f in fits for p in f["curve"]
                    if p["rel_mae"] <= best * (1 + MITSUBA_PLATEAU)), key=lambda x: x[0])
    reach = {}
    for f in fits:
        ts, _ = first_at_or_below([(p["seconds"], p["rel_mae"]) for p in f["curve"]],
                                  sp["rel_mae"])
        reach["x".join(map(str, f["resolution"]))] = ts
    return {"sphere_rel_mae": sp["rel_mae"], "sphere_model_seconds": sp["model_seconds"],
            "mitsuba_best_rel_mae": best, "mitsuba_best_resolution": best_f["resolution"],
            "mitsuba_plateau_seconds": t, "mitsuba_plateau_rel_mae": e,
            "mitsuba_plateau_resolution": f0["resolution"],
            "mitsuba_seconds_to_sphere_error": reach,
            "error_ratio_mitsuba_best_over_sphere": best / sp["rel_mae"]}


# --------------------------------------------------------------------------
# chart
# --------------------------------------------------------------------------

def log_axis(axis, percent: bool) -> None:
    """Log axis labelled at 1, 2 and 5 of each decade (plain or in percent), every label
    distinct; unlabelled minor ticks between."""
    from matplotlib.ticker import FuncFormatter, LogLocator, NullFormatter
    axis.set_major_locator(LogLocator(base=10, subs=(1.0, 2.0, 5.0)))
    axis.set_major_formatter(FuncFormatter(
        (lambda v, _: f"{100 * v:.3g}%") if percent else (lambda v, _: f"{v:g}")))
    axis.set_minor_locator(LogLocator(base=10, subs=(1.5, 3.0, 4.0, 6.0, 7.0, 8.0, 9.0)))
    axis.set_minor_formatter(NullFormatter())


def chart(stem: Path, sets: list[dict], meta: dict) -> list[Path]:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    cmap = plt.get_cmap("viridis")
    fig, axes = plt.subplots(len(sets), 2, figsize=(13, 5.2 * len(sets)), squeeze=False)
    for (ax_t, ax_p), s in zip(axes, sets):
        fits, lp, cmp_ = s["mitsuba"], s["lightprobe"], s["comparison"]
        cols = [cmap(0.15 + 0.6 * k / max(1, len(fits) - 1)) for k in range(len(fits))]
        for f, col in zip(fits, cols):
            w, h = f["resolution"]
            ax_t.plot([p["seconds"] for p in f["curve"]], [p["rel_mae"] for p in f["curve"]],
                      "-", color=col, lw=1.5,
                      label=f"Mitsuba {w}×{h} ({f['steps']} steps, "
                            f"{'converged' if f['converged'] else 'budget'})")
        cur = lp["curve"]
        ax_t.plot([r["fit_seconds"] for r in cur], [r["curve_eval"]["rel_mae"] for r in cur],
                  "s-", color="tab:red", ms=5, lw=1.2,
                  label=f"lightprobe {meta['rings']} rings, transport spp "
                        + "/".join(str(r["transport_spp"]) for r in cur))
        ax_t.plot([r["fit_seconds"] for r in lp["maps"]],
                  [r["curve_eval"]["rel_mae"] for r in lp["maps"]], "o", color="darkred", ms=5,
                  label="lightprobe maps of " + "/".join(str(r["rings"]) for r in lp["maps"])
                        + " rings")
        ax_t.set_xscale("log")
        ax_t.set_yscale("log")
        log_axis(ax_t.yaxis, True)
        log_axis(ax_t.xaxis, False)
        ax_t.set_xlabel("seconds on the fit clock (log)")
        ax_t.set_ylabel("relMAE, Mitsuba's render at the sidecar's spp")
        ax_t.set_title(f"references by {s['reference']['renderer']}: error against time",
                       fontsize=10)
        ax_t.grid(True, which="both", alpha=0.3)
        ax_t.legend(fontsize=7.5, loc="upper right")
        for marker, e in (("o", "mitsuba"), ("^", "lightprobe")):
            ax_p.plot([3 * r["cells"] for r in lp["maps"]],
                      [r["score"][e]["rel_mae"] for r in lp["maps"]], marker + "-",
                      color="tab:red", ms=5, lw=1, mfc="tab:red" if e == "mitsuba" else "white",
                      label=f"lightprobe rings, scored by {e}")
            ax_p.plot([f["parameters"] for f in fits], [f["score"][e]["rel_mae"] for f in fits],
                      marker + "--", color=cols[len(cols) // 2], ms=6, lw=1,
                      mfc=cols[len(cols) // 2] if e == "mitsuba" else "white",
                      label=f"Mitsuba lat-long, scored by {e}")
        ax_p.set_xscale("log")
        ax_p.set_yscale("log")
        log_axis(ax_p.yaxis, True)
        log_axis(ax_p.xaxis, False)
        ax_p.set_xlabel("parameters (3 × cells or texels, log)")
        ax_p.set_ylabel(f"relMAE at {s['score_spp']} spp")
        said = lambda v: f"{v['rings']} rings {'met' if v['fit']['met'] else 'not met'}"  # noqa: E731
        verdicts = cmp_["verdicts"]
        ax_p.set_title("final maps by size; the 20× goal (fit clock): "
                       + ", ".join(dict.fromkeys(said(verdicts[k]) for k in
                                                 ("default_map", "most_accurate_map"))),
                       fontsize=10)
        ax_p.grid(True, which="both", alpha=0.3)
        ax_p.legend(fontsize=7.5, loc="upper right")
    fig.suptitle(f"Envmap estimation, lightprobe and Mitsuba 3: {meta['scene_name']} "
                 f"({meta['width']}×{meta['height']}, {len(meta['views'])} views, "
                 f"max_bounces {meta['max_bounces']}, {meta['cpus']} CPUs)", fontsize=11)
    fig.tight_layout()
    assert_text_apart(fig, stem.name)
    paths = [stem.with_suffix(".png"), stem.with_suffix(".svg")]
    for p in paths:
        fig.savefig(p, dpi=120)
    plt.close(fig)
    return paths


# --------------------------------------------------------------------------

def finite(x):
    """x for JSON: an infinite ratio (Mitsuba never reached the error) becomes null."""
    if isinstance(x, float) and math.isinf(x):
        return None
    if isinstance(x, dict):
        return {k: finite(v) for k, v in x.items()}
    if isinstance(x, list):
        return [finite(v) for v in x]
    return x


def parse_res(s: str) -> list[tuple[int, int]]:
    return [tuple(int(x) for x in part.lower().split("x")) for part in s.split(",") if part]


def ints(s: str) -> list[int]:
    return [int(x) for x in s.split(",") if x.strip()]


def summary(sets: list[dict], sp: dict | None, goals: dict) -> None:
    log("\n=== summary ===")
    for s in sets:
        c = s["comparison"]
        log(f"references by {s['reference']['renderer']}:")
        for r in s["lightprobe"]["maps"]:
            log(f"  lightprobe {r['rings']:2d} rings ({3 * r['cells']:5d} parameters): fit "
                f"{r['fit_seconds']:6.2f} s; relMAE by Mitsuba {r['score']['mitsuba']['rel_mae']:.4f}"
                f", by lightprobe {r['score']['lightprobe']['rel_mae']:.4f}")
        for f in s["mitsuba"]:
            w, h = f["resolution"]
            log(f"  Mitsuba {w}x{h} ({f['parameters']:5d} parameters): {f['steps']} steps, "
                f"{f['stopped']}; best checkpoint {f['best']['rel_mae']:.4f} at "
                f"{f['best']['seconds']:.1f} s; relMAE by Mitsuba "
                f"{f['score']['mitsuba']['rel_mae']:.4f}, by lightprobe "
                f"{f['score']['lightprobe']['rel_mae']:.4f}")
        for name, v in c["verdicts"].items():
            for clock in ("fit", "process"):
                g = v[clock]
                ratio = g["speed_ratio"]
                said = (f"never reached by Mitsuba (its longest run is "
                        f"{v['ratio_at_least'][clock]:.1f}x)" if ratio == math.inf
                        else f"{ratio:.1f}x")
                log(f"  {name} ({v['rings']} rings), {clock} clock: "
                    f"{'MET' if g['met'] else 'NOT MET'} -- speed {said}"
                    f" ({'ok' if g['speed_half'] else 'short'}), error "
                    f"{'<=' if g['error_half'] else '>'} Mitsuba's best under both evaluators"
                    f" ({v['rel_mae']['mitsuba']:.4f}/{v['rel_mae']['lightprobe']:.4f} vs "
                    f"{v['mitsuba_best_rel_mae']['mitsuba']:.4f}/"
                    f"{v['mitsuba_best_rel_mae']['lightprobe']:.4f}), Mitsuba "
                    f"{'converged' if g['mitsuba_converged'] else 'NOT converged'}")
        for z in c["comparable_sizes"]:
            w, h = z["mitsuba_resolution"]
            log(f"  comparable sizes: Mitsuba {w}x{h} ({z['mitsuba_parameters']}) vs "
                f"{z['lightprobe_rings']} rings ({z['lightprobe_parameters']}): more accurate "
                f"by Mitsuba's evaluator {z['more_accurate']['mitsuba']}, by lightprobe's "
                f"{z['more_accurate']['lightprobe']}")
    if sp:
        vs = sp["vs_mitsuba"]
        log(f"sphere model ({sp['model']}): relMAE {sp['rel_mae']:.4f} in "
            f"{sp['model_seconds']:.1f} s; Mitsuba's best checkpoint "
            f"{vs['mitsuba_best_rel_mae']:.4f} (plateau at {vs['mitsuba_plateau_seconds']:.1f} s)")
    for k, g in goals.items():
        log(f"GOAL {k}: {'MET' if g['met'] else 'NOT MET'}")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scene", type=Path, default=ms.DEFAULT_SCENE)
    ap.add_argument("--bin", type=Path, default=ms.DEFAULT_BIN, help="lightprobe binary")
    ap.add_argument("--out", type=Path, default=ms.REPO / "out" / "bench_estimate",
                    help="chart + JSON go here (default <repo>/out/bench_estimate, git-ignored)")
    ap.add_argument("--workdir", type=Path, default=None,
                    help="references and both tools' outputs (default: a new temp dir)")
    ap.add_argument("--references", default="lightprobe,mitsuba",
                    help="who renders the references; the comparison runs once per renderer")
    ap.add_argument("--rings", type=int, default=9, help="lightprobe's default map")
    ap.add_argument("--rings-list", type=ints, default=[5, 9, 13, 17, 21, 25, 41],
                    help="lightprobe's map sizes (21 and 41 rings have about as many "
                         "parameters as 32x16 and 64x32 texels)")
    ap.add_argument("--curve-spp", type=ints, default=[64, 128, 256],
                    help="more transport spp at --rings for lightprobe's time/error curve")
    ap.add_argument("--lp-repeat", type=int, default=3,
                    help="runs of the default map (median times)")
    ap.add_argument("--spheres", type=int, default=2, metavar="K",
                    help="also `estimate --model spheres:K` on lightprobe's references; 0 = skip")
    ap.add_argument("--mi-res", type=parse_res, default=parse_res("16x8,32x16,64x32"))
    ap.add_argument("--mi-steps", type=int, default=1500, help="Mitsuba's step budget")
    ap.add_argument("--mi-patience", type=int, default=200,
                    help="converged: best error gained < --mi-min-gain over this many steps")
    ap.add_argument("--mi-min-gain", type=float, default=0.005)
    ap.add_argument("--mi-spp", type=int, default=16, help="spp per view and step")
    ap.add_argument("--mi-lr", type=float, default=0.3)
    ap.add_argument("--mi-eval-every", type=int, default=10)
    ap.add_argument("--score-spp", type=int, default=2048,
                    help="spp of both evaluators' renders of the final maps")
    ap.add_argument("--wait-idle", type=float, default=0.0, metavar="SECONDS",
                    help="before each timed run wait up to this long for other processes to "
                         "use < 0.2 cores; what they used is recorded either way")
    ap.add_argument("--replot", type=Path, default=None,
                    help="only recompute the comparison and redraw the chart from a "
                         "bench_estimate.json (into --out)")
    ap.add_argument("--test-verdict", action="store_true", help="check the verdict logic")
    ap.add_argument("--quick", action="store_true",
                    help="smoke test: lightprobe's references, 9 rings, Mitsuba 16x8 for at "
                         "most 60 steps, 128-spp scores, no sphere model")
    args = ap.parse_args()
    if args.test_verdict:
        test_verdict()
        return 0
    args.out.mkdir(parents=True, exist_ok=True)
    stem = args.out / "estimate_vs_mitsuba"
    if args.replot:
        j = json.loads(args.replot.read_text())
        for s in j["sets"]:
            s["comparison"] = compare(s["lightprobe"], s["mitsuba"],
                                      j["mitsuba_import_seconds"], j["meta"]["rings"])
        chart(stem, j["sets"], j["meta"])
        (args.out / "bench_estimate.json").write_text(
            json.dumps(finite(j), indent=1, allow_nan=False) + "\n")
        log(f"redrew {stem}.png/.svg from {args.replot}")
        return 0
    if args.quick:
        args.references, args.rings_list, args.curve_spp, args.lp_repeat = "lightprobe", [9], [], 1
        args.mi_res, args.mi_steps, args.mi_patience = [(16, 8)], 60, 30
        args.score_spp, args.spheres = 128, 0
    t_start = time.time()
    work = args.workdir or Path(tempfile.mkdtemp(prefix="bench_estimate_"))
    work.mkdir(parents=True, exist_ok=True)
    log(f"workdir {work}; out {args.out}; {os.cpu_count()} CPUs; load average {load()}")

    t0 = time.perf_counter()
    variant = ms.set_variant(require_llvm=True)
    import drjit as dr
    import mitsuba as mi
    import_seconds = time.perf_counter() - t0
    desc = ms.described_scene(args.scene, args.bin)
    st = desc["settings"]
    views = [c["name"] for c in desc["cameras"]]
    meshes = ms.load_meshes(ms.sidecar_gltf(args.scene))
    binary = binary_provenance(args.bin)
    log(f"lightprobe {binary['path']} (sha256 {binary['sha256'][:12]}, HEAD "
        f"{binary['git_head']}); Mitsuba {mi.__version__} {variant}, import "
        f"{import_seconds:.1f} s")

    sets, sp = [], None
    for renderer in args.references.split(","):
        sub = work / f"refs_by_{renderer}"
        ref = render_references(args, desc, meshes, renderer, sub / "reference")
        refs = {v: read_rgba(Path(ref["dir"]) / f"{v}.exr") for v in views}
        log(f"\nreferences by {renderer}: {views}, {st['spp']} spp ({ref['seconds']:.1f} s)")
        lp = run_lightprobe_suite(args, Path(ref["dir"]), sub)
        if renderer == "lightprobe" and args.spheres:
            sp = run_sphere_suite(args, Path(ref["dir"]), sub)
        fits = []
        for (w, h) in args.mi_res:
            log(f"  Mitsuba {w}x{h}: Adam lr {args.mi_lr}, {args.mi_spp} spp/view/step, until "
                f"converged (< {100 * args.mi_min_gain:g}% over {args.mi_patience} steps) or "
                f"{args.mi_steps} steps")
            fit = MitsubaFit(args, desc, meshes, refs, w, h, len(fits))
            if args.wait_idle:
                wait_idle(args.wait_idle)
            with CpuMonitor() as cm:
                f = fit.run()
            f["cpu"] = cm.result
            fits.append(f)
            log(f"  -> {f['stopped']} at step {f['steps']}: best {f['best']['rel_mae']:.4f} at "
                f"step {f['best']['step']} ({f['best']['seconds']:.1f} s); other processes "
                f"{cm.result['other_cores']:.2f} cores")
        # the evaluators: curves at the sidecar's spp by Mitsuba; final maps by both
        k = 0
        for r in lp["curve"] + [r for r in lp["maps"] if r not in lp["curve"]]:
            k += 1
            r["curve_eval"] = score_by_mitsuba(args, desc, meshes, refs,
                                               Path(r["out"]) / "envmap.exr", st["spp"],
                                               2_000_000 + 10 * k)
        for r in lp["maps"]:
            k += 1
            r["score"] = {
                "mitsuba": score_by_mitsuba(args, desc, meshes, refs,
                                            Path(r["out"]) / "envmap.exr", args.score_spp,
                                            3_000_000 + 10 * k),
                "lightprobe": score_by_lightprobe(args, refs, Path(r["out"]) / "envmap.ron",
                                                  args.score_spp, 10_000 + k,
                                                  sub / f"score_lp_{r['rings']}", False)}
        for f in fits:
            k += 1
            w, h = f["resolution"]
            best = f.pop("best_map")
            raw, fine = sub / f"mitsuba_{w}x{h}.exr", sub / f"mitsuba_{w}x{h}_fine.exr"
            write_exr(raw, best)
            write_exr(fine, mitsuba_map_on_fine_grid(best))
            f["map"] = str(raw)
            f["score"] = {
                "mitsuba": score_by_mitsuba(args, desc, meshes, refs, best, args.score_spp,
                                            3_000_000 + 10 * k),
                "lightprobe": score_by_lightprobe(args, refs, fine, args.score_spp, 10_000 + k,
                                                  sub / f"score_mi_{w}x{h}", True)}
        sets.append({"reference": ref, "score_spp": args.score_spp, "lightprobe": lp,
                     "mitsuba": fits,
                     "comparison": compare(lp, fits, import_seconds, args.rings)})

    goals = {}
    for s in sets:
        for name, v in s["comparison"]["verdicts"].items():
            goals[f"speed_20x_at_equal_or_lower_error_{name}_refs_by_"
                  f"{s['reference']['renderer']}"] = {
                "rings": v["rings"], **v["fit"], "process_clock": v["process"]}
    for k, g in goals.items():       # never "met" with a half false, on either clock
        for v in (g, g["process_clock"]):
            assert v["met"] == (v["speed_half"] and v["error_half"]
                                and v["mitsuba_converged"]), (k, v)
    big = [r for r in sets[0]["lightprobe"]["maps"] if r["rings"] == 25]
    if big:
        b = big[0]
        goals["peak_memory_25_rings_under_1GiB"] = {
            "peak_bytes": b["peak_bytes"], "max_rss_bytes": b["max_rss_bytes"],
            "met": max(b["peak_bytes"], b["max_rss_bytes"]) < GIB}
    if sp:
        sp["vs_mitsuba"] = sphere_vs_mitsuba(sp, sets[0]["mitsuba"])
        goals["spheres_under_15s"] = {"model_seconds": sp["model_seconds"],
                                      "met": sp["goal_under_15_s_met"]}
    meta = {"scene_name": Path(args.scene).stem, "width": st["width"], "height": st["height"],
            "views": views, "max_bounces": st["max_bounces"], "cpus": os.cpu_count(),
            "rings": args.rings}
    paths = chart(stem, sets, meta)
    result = {
        "protocol": __doc__, "scene": str(args.scene), "settings": st, "meta": meta,
        "lightprobe_binary": binary, "lightprobe_binary_after": binary_provenance(args.bin),
        "mitsuba_version": mi.__version__, "mitsuba_variant": variant,
        "mitsuba_threads": dr.thread_count(), "mitsuba_import_seconds": import_seconds,
        "sets": sets, "spheres": sp, "goals": goals,
        "charts": [str(p) for p in paths], "seconds": time.time() - t_start,
        "args": {k: (str(v) if isinstance(v, Path) else v) for k, v in vars(args).items()},
    }
    jpath = args.out / "bench_estimate.json"
    jpath.write_text(json.dumps(finite(result), indent=1, default=float, allow_nan=False)
                     + "\n")
    summary(sets, sp, goals)
    log(f"wrote {', '.join(map(str, paths))} and {jpath} ({time.time() - t_start:.0f} s)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
