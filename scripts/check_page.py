#!/usr/bin/env python3
"""The results page in a real browser: headless Chromium (Debian's `chromium`) opens an
estimate's index.html over the DevTools protocol, and the check fails unless

- every image loaded (complete, with a natural size), and no image is missing;
- the console logged no error, and the page threw nothing (a missing file logs one);
- every number tagged `data-json` equals report.json's value at that path, and its text is
  that value in its `data-format` (the rules of lightprobe's page.rs, written again here);
- the page shows the figures it must (`expected_numbers`: headline errors, every view, every
  candidate of a selection, every sphere light).
  A sweep's page (`lightprobe report DIR`) has no report.json and tags no number: its images
  and console are checked.

It first proves it can fail: on a copy of the page with one image deleted, one with a number's
value changed and one with a number's text changed, it must report the fault. A screenshot of
the whole page is saved.

    check_page.py OUT [--screenshot page.png [--screenshot-height H]] [--chromium chromium]
"""

import argparse
import base64
import json
import math
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import time
import urllib.parse
import urllib.request
from pathlib import Path

import websocket  # websocket-client


def fmt(value, kind):
    """A number as page.rs shows it (Rust's `{:.N}` rounds the exact binary value, as
    Python's format does)."""
    if kind == "percent":
        return f"{100 * value:.2f}%"
    if kind == "seconds":
        return f"{value:.2f} s"
    if kind == "ratio":
        return f"×{value:.2f}"
    if kind == "degrees":
        return f"{value:.2f}°"
    if kind == "metres":
        return f"{value:.3f} m"
    if kind == "mib":
        return f"{value / (1024 * 1024):.0f} MiB"
    if kind == "scientific":
        # Rust's {:.2e}: mantissa with 2 decimals, exponent without sign padding or '+'.
        m, e = f"{value:.2e}".split("e")
        return f"{m}e{int(e)}"
    if kind == "significant":
        digits = 0 if value == 0 or not math.isfinite(value) else \
            max(0, 3 - math.floor(math.log10(abs(value))))
        return f"{value:.{digits}f}"
    if kind == "integer":
        return f"{value:.0f}"
    raise ValueError(f"unknown data-format {kind!r}")


def at(report, path):
    v = report
    for key in path.split("."):
        if isinstance(v, list):
            v = v[int(key)] if key.isdigit() and int(key) < len(v) else None
        elif isinstance(v, dict):
            v = v.get(key)
        else:
            return None
    return v


# What the self-tests leave out of their copies of OUT: files the page links but does not load.
BULK = shutil.ignore_patterns("*.exr", "mitsuba", "blender_textures", "*.glb", "*.gltf")


class Browser:
    """One headless Chromium with one page, driven over the DevTools protocol."""

    def __init__(self, binary):
        self.profile = tempfile.mkdtemp(prefix="lp-chromium-")
        self.proc = self.ws = None
        try:
            # Its own process group, so that close() ends Chromium's helpers too.
            self.proc = subprocess.Popen(
                [binary, "--headless=new", "--no-sandbox", "--disable-gpu",
                 "--no-first-run", "--disable-extensions", "--hide-scrollbars",
                 f"--user-data-dir={self.profile}", "--remote-debugging-port=0",
                 "about:blank"],
                stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True)
            self.ws = self.connect(binary)
        except BaseException:
            self.close()
            raise
        self.next_id = 0
        self.events = []

    def connect(self, binary):
        """The DevTools websocket of Chromium's first page, once it lists one (60 s)."""
        port_file = Path(self.profile) / "DevToolsActivePort"
        deadline = time.time() + 60
        while time.time() < deadline:
            if self.proc.poll() is not None:
                break
            if port_file.exists() and port_file.read_text().strip():
                port = port_file.read_text().split()[0]
                try:
                    targets = json.load(
                        urllib.request.urlopen(f"http://127.0.0.1:{port}/json/list", timeout=5))
                except OSError:
                    targets = []
                pages = [t for t in targets if t.get("type") == "page"]
                if pages:
                    return websocket.create_connection(pages[0]["webSocketDebuggerUrl"],
                                                       timeout=60, suppress_origin=True)
            time.sleep(0.1)
        raise SystemExit(f"check_page: {binary} did not open its DevTools endpoint")

    def call(self, method, **params):
        self.next_id += 1
        self.ws.send(json.dumps({"id": self.next_id, "method": method, "params": params}))
        while True:
            msg = json.loads(self.ws.recv())
            if msg.get("id") == self.next_id:
                if "error" in msg:
                    raise RuntimeError(f"{method}: {msg['error']}")
                return msg.get("result", {})
            self.events.append(msg)

    def wait_for(self, event, seconds=60):
        deadline = time.time() + seconds
        while time.time() < deadline:
            if any(e.get("method") == event for e in self.events):
                return
            self.events.append(json.loads(self.ws.recv()))
        raise RuntimeError(f"no {event} within {seconds} s")

    def evaluate(self, expression):
        r = self.call("Runtime.evaluate", expression=expression, returnByValue=True,
                      awaitPromise=True)
        if "exceptionDetails" in r:
            raise RuntimeError(f"evaluating the page failed: {r['exceptionDetails']}")
        return r["result"]["value"]

    def close(self):
        if self.ws is not None:
            self.ws.close()
        if self.proc is not None:
            for sig, wait in ((signal.SIGTERM, 10), (signal.SIGKILL, 10)):
                try:
                    os.killpg(self.proc.pid, sig)
                    self.proc.wait(wait)
                    break
                except ProcessLookupError:
                    break
                except subprocess.TimeoutExpired:
                    continue
        shutil.rmtree(self.profile, ignore_errors=True)


def expected_numbers(report):
    """Paths of report.json the page must show: the headline figures, every view's error,
    every candidate of a selection, every sphere light, every fitted exposure (where the
    report has them)."""
    paths = ["rings", "cells", "transport_spp", "timings.total_seconds", "memory.peak_bytes"]
    for key in ("rel_mae", "noise_floor_rel_mae", "representation_limit_rel_mae",
                "fit_test.residual_over_noise", "spheres.rel_mae"):
        if at(report, key) is not None:
            paths.append(key)
    for i, v in enumerate(report["views"]):
        if v.get("estimate") is not None:
            paths.append(f"views.{i}.estimate.rel_mae")
    for key in ("model_selection", "rings_selection"):
        for i, _ in enumerate((report.get(key) or {}).get("candidates", [])):
            paths.append(f"{key}.candidates.{i}.validation_rel_mae")
    spheres = report.get("spheres") or {}
    for i, _ in enumerate(spheres.get("lights", [])):
        paths.append(f"spheres.lights.{i}.light.radius")
    for i, _ in enumerate(spheres.get("views", [])):
        paths.append(f"spheres.views.{i}.rel_mae")
    for i, _ in enumerate(report.get("light_recovery", [])):
        paths.append(f"light_recovery.{i}.angle_error_degrees")
    for i, _ in enumerate((report.get("exposure") or {}).get("relative", [])):
        paths.append(f"exposure.relative.{i}.exposure")
    return paths


PROBE = """(async () => {
  await Promise.all(Array.from(document.images).map(i => i.decode().catch(() => null)));
  return {
    images: Array.from(document.images).map(i => ({
      src: i.getAttribute('src'), complete: i.complete, width: i.naturalWidth})),
    numbers: Array.from(document.querySelectorAll('[data-json]')).map(e => ({
      path: e.dataset.json, value: e.dataset.value, format: e.dataset.format,
      text: e.textContent})),
    height: Math.ceil(document.documentElement.scrollHeight),
  };
})()"""


def inspect(browser, out, screenshot=None, shot_height=None):
    """Loads OUT/index.html; returns the list of faults found (empty: the page is right)."""
    browser.events.clear()
    browser.call("Page.enable")
    browser.call("Runtime.enable")
    browser.call("Log.enable")
    browser.call("Page.navigate", url=(Path(out) / "index.html").resolve().as_uri())
    browser.wait_for("Page.loadEventFired")
    page = browser.evaluate(PROBE)
    faults = []
    for e in browser.events:
        m, p = e.get("method"), e.get("params", {})
        if m == "Runtime.consoleAPICalled" and p.get("type") == "error":
            faults.append(f"console error: {p.get('args')}")
        elif m == "Runtime.exceptionThrown":
            faults.append(f"exception: {p.get('exceptionDetails', {}).get('text')}")
        elif m == "Log.entryAdded" and p.get("entry", {}).get("level") == "error":
            faults.append(f"console error: {p['entry'].get('text')} {p['entry'].get('url', '')}")
    if not page["images"]:
        faults.append("the page shows no image")
    for img in page["images"]:
        if not img["complete"] or img["width"] == 0:
            faults.append(f"image {img['src']} did not load")
    report_file = Path(out) / "report.json"
    report = json.loads(report_file.read_text()) if report_file.exists() else None
    if report is not None and not page["numbers"]:
        faults.append("the page tags no number")
    if report is None and page["numbers"]:
        faults.append("the page tags numbers but there is no report.json")
    if report is not None:
        shown = {n["path"] for n in page["numbers"]}
        for path in expected_numbers(report):
            if path not in shown:
                faults.append(f"the page does not show {path}")
    for n in page["numbers"]:
        want = at(report, n["path"])
        shown = json.loads(n["value"])
        if shown != want and not (isinstance(want, float) and isinstance(shown, (int, float))
                                  and math.isclose(shown, want, rel_tol=0, abs_tol=0)):
            faults.append(f"{n['path']}: the page holds {shown!r}, report.json {want!r}")
            continue
        text = "—" if want is None else fmt(want, n["format"])
        if n["text"] != text:
            faults.append(f"{n['path']}: shown {n['text']!r}, its value reads {text!r}")
    if screenshot:
        height = min(page["height"], shot_height or 8000)
        browser.call("Emulation.setDeviceMetricsOverride", width=1440,
                     height=height, deviceScaleFactor=1, mobile=False)
        shot = browser.call("Page.captureScreenshot", format="png",
                            clip={"x": 0, "y": 0, "width": 1440, "height": height, "scale": 1})
        Path(screenshot).write_bytes(base64.b64decode(shot["data"]))
    return faults, page


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("out", help="an estimate's output folder (holding index.html)")
    ap.add_argument("--screenshot", help="save a screenshot of the whole page here")
    ap.add_argument("--screenshot-height", type=int,
                    help="only the top this many pixels (the README's docs/page.png: 1400)")
    ap.add_argument("--chromium", default=shutil.which("chromium") or "chromium")
    a = ap.parse_args()
    # A stopped check (SIGTERM, Ctrl-C) still ends Chromium and removes its profile.
    signal.signal(signal.SIGTERM, lambda *_: sys.exit("check_page: stopped"))
    browser = Browser(a.chromium)
    try:
        faults, page = inspect(browser, a.out, a.screenshot, a.screenshot_height)
        if not page["images"]:
            raise SystemExit(f"check_page: FAIL {a.out}/index.html shows no image")
        print(f"check_page: {len(page['images'])} images, {len(page['numbers'])} numbers "
              f"checked in {a.out}/index.html")
        # The check must see faults: one image gone, one number changed.
        with tempfile.TemporaryDirectory() as tmp:
            copy = Path(tmp) / "out"
            shutil.copytree(a.out, copy, ignore=BULK)
            gone = page["images"][-1]["src"]
            os.remove(copy / urllib.parse.unquote(gone))
            lost, _ = inspect(browser, copy)
            if not any(gone in f for f in lost):
                faults.append(f"self-test: deleting {gone} went unnoticed ({lost})")
            if page["numbers"]:
                os.remove(copy / "index.html")
                shutil.copytree(a.out, copy, dirs_exist_ok=True, ignore=BULK)
                html = (copy / "index.html").read_text()
                first = page["numbers"][0]
                tag = f'data-json="{first["path"]}" data-value="'
                i = html.index(tag) + len(tag)
                j = html.index('"', i)
                value = json.loads(html[i:j])
                changed = json.dumps(value * 1.01 if value else 1)
                (copy / "index.html").write_text(html[:i] + changed + html[j:])
                wrong, _ = inspect(browser, copy)
                if not any(first["path"] in f for f in wrong):
                    faults.append(f"self-test: a changed {first['path']} went unnoticed")
                # The text of a percentage, its value left as it is.
                pct = next(n for n in page["numbers"] if n["format"] == "percent"
                           and n["text"] != "—")
                cell = f'data-json="{pct["path"]}"'
                i = html.index(cell)
                i = html.index(">", i) + 1
                j = html.index("<", i)
                (copy / "index.html").write_text(html[:i] + "1" + html[i:j] + html[j:])
                wrong, _ = inspect(browser, copy)
                if not any(pct["path"] in f and "shown" in f for f in wrong):
                    faults.append(f"self-test: a misprinted {pct['path']} went unnoticed")
    finally:
        browser.close()
    for f in faults:
        print(f"check_page: FAIL {f}")
    if faults:
        sys.exit(1)
    if page["numbers"]:
        print("check_page: ok (images loaded, no console error, numbers equal report.json; "
              "a deleted image, a changed number and a misprinted one are caught)")
    else:
        print("check_page: ok (images loaded, no console error; a deleted image is caught)")


if __name__ == "__main__":
    main()
