#!/usr/bin/env python3
"""Writes the bundled scene with a soft shadow baked into the table's texture, as a
photographed texture carries the light it was shot under: `scenes/tabletop/baked_shadow/`
gets `table_baked.png` (the table texture from tabletop.glb, darkened to 40% at the centre
of a soft blob, in linear light) and `baked_shadow.ron` (the bundled sidecar with that map
as the table's albedo).

    .venv/bin/python scripts/make_baked_shadow.py

Render the references from the bundled scene (the true texture), then estimate in this one
with `--reference` and `--fit-albedo texels`: the estimate should take the shadow out.
Needs numpy and Pillow (scripts/requirements.txt); deterministic.
"""

import io
import json
import struct
from pathlib import Path

import numpy as np
from PIL import Image

ROOT = Path(__file__).resolve().parent.parent
SCENE = ROOT / "scenes" / "tabletop"
OUT = SCENE / "baked_shadow"

# The blob in texture coordinates (the table's top repeats the texture 2 × 2, so it shows
# four times on the table), its width (standard deviation) and its darkest factor.
CENTRE = (0.25, 0.85)
SIGMA = (0.12, 0.16)
DARKEST = 0.4


def table_texture():
    data = (SCENE / "tabletop.glb").read_bytes()
    json_len = struct.unpack("<I", data[12:16])[0]
    doc = json.loads(data[20 : 20 + json_len])
    binary = data[20 + json_len + 8 :]
    table = next(m for m in doc["materials"] if m["name"] == "table")
    texture = doc["textures"][table["pbrMetallicRoughness"]["baseColorTexture"]["index"]]
    view = doc["bufferViews"][doc["images"][texture["source"]]["bufferView"]]
    start = view.get("byteOffset", 0)
    return Image.open(io.BytesIO(binary[start : start + view["byteLength"]])).convert("RGB")


def srgb_to_linear(c):
    return np.where(c <= 0.04045, c / 12.92, ((c + 0.055) / 1.055) ** 2.4)


def linear_to_srgb(c):
    return np.where(c <= 0.0031308, c * 12.92, 1.055 * np.power(c, 1 / 2.4) - 0.055)


def main():
    image = table_texture()
    w, h = image.size
    linear = srgb_to_linear(np.asarray(image, dtype=np.float64) / 255.0)
    u = (np.arange(w) + 0.5) / w
    v = (np.arange(h) + 0.5) / h
    uu, vv = np.meshgrid(u, v)
    # Wrapped distance, so that the blob stays soft across the texture's edges.
    du = (uu - CENTRE[0] + 0.5) % 1.0 - 0.5
    dv = (vv - CENTRE[1] + 0.5) % 1.0 - 0.5
    blob = np.exp(-0.5 * ((du / SIGMA[0]) ** 2 + (dv / SIGMA[1]) ** 2))
    shade = 1.0 - (1.0 - DARKEST) * blob
    baked = linear_to_srgb(np.clip(linear * shade[..., None], 0.0, 1.0))
    OUT.mkdir(parents=True, exist_ok=True)
    Image.fromarray(np.round(baked * 255.0).astype(np.uint8)).save(OUT / "table_baked.png")
    sidecar = (SCENE / "tabletop.ron").read_text()
    sidecar = sidecar.replace('gltf: "tabletop.glb"', 'gltf: "../tabletop.glb"')
    sidecar = sidecar.replace(
        "    envmap:", '    albedo: { "table": Map("table_baked.png") },\n    envmap:', 1
    )
    header = (
        "// Made by scripts/make_baked_shadow.py: the bundled scene with a soft shadow baked\n"
        "// into the table's texture (down to 40% of the true albedo). References rendered from\n"
        "// ../tabletop.ron show the true texture; estimate here with --fit-albedo texels.\n"
    )
    lines = [l for l in sidecar.splitlines() if not l.startswith("//")]
    (OUT / "baked_shadow.ron").write_text(header + "\n".join(lines) + "\n")


if __name__ == "__main__":
    main()
