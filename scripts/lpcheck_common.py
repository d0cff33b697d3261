"""Shared helpers for the external-oracle checks (check_trimesh.py, check_exr_oiio.py).

Nothing here depends on lightprobe's internals: it runs the CLI, reads its JSON
and reads its EXR files with Mitsuba's Bitmap class (an independent EXR reader
that is already in scripts/requirements.txt).
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parent.parent
DEFAULT_LIGHTPROBE = REPO / "target" / "release" / "lightprobe"
DEFAULT_SCENE = REPO / "scenes" / "tabletop" / "tabletop.ron"


class CheckError(Exception):
    """A problem that prevents the check from running (as opposed to a FAIL)."""


def log(msg: str = "") -> None:
    print(msg, flush=True)


def find_lightprobe(path: Path, wait_seconds: float = 30.0) -> Path:
    """Return the binary's path; wait a little if it is missing, because a
    concurrent `cargo build` replaces it (briefly absent while linking)."""
    deadline = time.monotonic() + wait_seconds
    announced = False
    while True:
        if path.is_file() and os.access(path, os.X_OK):
            return path
        if time.monotonic() >= deadline:
            raise CheckError(
                f"lightprobe binary not found or not executable: {path}\n"
                f"  build it with `cargo build --release`, or pass --lightprobe PATH")
        if not announced:
            log(f"waiting up to {wait_seconds:.0f} s for {path} to appear ...")
            announced = True
        time.sleep(1.0)


def run(cmd: list, what: str) -> subprocess.CompletedProcess:
    """Run a command, capture its output, raise CheckError with its stderr if it fails."""
    try:
        proc = subprocess.run([str(c) for c in cmd], capture_output=True, text=True,
                              stdin=subprocess.DEVNULL)
    except OSError as e:
        raise CheckError(f"{what}: cannot run {cmd[0]}: {e}") from e
    if proc.returncode != 0:
        raise CheckError(f"{what} failed (exit {proc.returncode}): {' '.join(map(str, cmd))}\n"
                         f"--- stderr ---\n{proc.stderr.strip()}\n--- stdout ---\n"
                         f"{proc.stdout.strip()[-2000:]}")
    return proc


def lightprobe_info(binary: Path, scene: Path) -> dict:
    proc = run([binary, "info", scene], "lightprobe info")
    try:
        return json.loads(proc.stdout)
    except json.JSONDecodeError as e:
        raise CheckError(f"lightprobe info did not print JSON: {e}\n{proc.stdout[:500]}") from e


def gltf_path_from_sidecar(scene: Path) -> Path:
    """The glTF file a RON sidecar names, resolved relative to the sidecar."""
    import scene_truth
    try:
        return scene_truth.sidecar_gltf(scene)
    except (scene_truth.TruthError, OSError) as e:
        raise CheckError(str(e)) from e


_MI = None


def _mitsuba():
    global _MI
    if _MI is None:
        try:
            import mitsuba as mi
        except ImportError as e:
            raise CheckError("cannot import mitsuba (the EXR reader); run "
                             "`bash scripts/setup-venv.sh` and use .venv/bin/python") from e
        mi.set_variant("scalar_rgb")
        _MI = mi
    return _MI


def read_exr(path: Path) -> tuple[np.ndarray, list[str], str]:
    """Read an EXR with Mitsuba's Bitmap: (pixels HxWxC, channel names, component format).

    Pixels are returned exactly as stored (no colour conversion is applied to a
    linear float RGB/RGBA EXR)."""
    mi = _mitsuba()
    try:
        bmp = mi.Bitmap(str(path))
    except Exception as e:  # noqa: BLE001 - mitsuba raises RuntimeError subclasses
        raise CheckError(f"Mitsuba could not read {path}: {e}") from e
    names = [f.name for f in bmp.struct_()]
    fmt = str(bmp.component_format()).split(".")[-1]
    arr = np.array(bmp, copy=True)
    if arr.ndim == 2:
        arr = arr[..., None]
    return arr, names, fmt
