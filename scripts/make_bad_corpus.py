#!/usr/bin/env python3
"""Writes the bad-input corpus of glTF/GLB files under tests/bad/ (and the small valid GLB
that seeds the glTF fuzzer). Standard library only; deterministic. Run from anywhere:

    python3 scripts/make_bad_corpus.py

Each case is one file; tests/cli.rs says what error each must give."""
import base64, json, os, struct, zlib

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
BAD = os.path.join(ROOT, "tests", "bad")
SEEDS = os.path.join(ROOT, "fuzz", "seeds", "gltf")


def png_2x2():
    raw = b"".join(b"\x00" + bytes([200, 120, 40] * 2) for _ in range(2))
    def chunk(t, d):
        return struct.pack(">I", len(d)) + t + d + struct.pack(">I", zlib.crc32(t + d) & 0xFFFFFFFF)
    return (b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", struct.pack(">IIBBBBB", 2, 2, 8, 2, 0, 0, 0))
            + chunk(b"IDAT", zlib.compress(raw)) + chunk(b"IEND", b""))


def triangle_bin():
    pos = struct.pack("<9f", 0, 0, 0, 1, 0, 0, 0, 0, -1)
    nrm = struct.pack("<9f", 0, 1, 0, 0, 1, 0, 0, 1, 0)
    uv = struct.pack("<6f", 0, 0, 1, 0, 0, 1)
    idx = struct.pack("<3I", 0, 1, 2)
    return pos + nrm + uv + idx


def base_gltf(bin_uri, *, mode=4, camera=True, mesh=True, index_count=3, image=None):
    """A one-triangle scene with a textured material and (optionally) a camera."""
    doc = {
        "asset": {"version": "2.0"},
        "buffers": [{"byteLength": 108, "uri": bin_uri}],
        "bufferViews": [
            {"buffer": 0, "byteOffset": 0, "byteLength": 36},
            {"buffer": 0, "byteOffset": 36, "byteLength": 36},
            {"buffer": 0, "byteOffset": 72, "byteLength": 24},
            {"buffer": 0, "byteOffset": 96, "byteLength": 12},
        ],
        "accessors": [
            {"bufferView": 0, "componentType": 5126, "count": 3, "type": "VEC3", "min": [0, 0, -1], "max": [1, 0, 0]},
            {"bufferView": 1, "componentType": 5126, "count": 3, "type": "VEC3"},
            {"bufferView": 2, "componentType": 5126, "count": 3, "type": "VEC2"},
            {"bufferView": 3, "componentType": 5125, "count": index_count, "type": "SCALAR"},
        ],
        "materials": [{"name": "m", "pbrMetallicRoughness": {"baseColorFactor": [0.5, 0.5, 0.5, 1]}}],
        "meshes": [{"name": "tri", "primitives": [{"attributes": {"POSITION": 0, "NORMAL": 1, "TEXCOORD_0": 2}, "indices": 3, "material": 0, "mode": mode}]}],
        "cameras": [{"type": "perspective", "perspective": {"yfov": 0.8, "znear": 0.01}}],
        "nodes": [],
        "scenes": [{"nodes": []}],
        "scene": 0,
    }
    if mesh:
        doc["nodes"].append({"name": "tri", "mesh": 0})
    if camera:
        doc["nodes"].append({"name": "cam", "camera": 0, "translation": [0.2, 1.0, 1.0]})
    doc["scenes"][0]["nodes"] = list(range(len(doc["nodes"])))
    if image is not None:
        doc["images"] = [image]
        doc["samplers"] = [{}]
        doc["textures"] = [{"source": 0, "sampler": 0}]
        doc["materials"][0]["pbrMetallicRoughness"]["baseColorTexture"] = {"index": 0}
    return doc


def data_uri(b, mime="application/octet-stream"):
    return f"data:{mime};base64," + base64.b64encode(b).decode()


def glb(doc, binary):
    js = json.dumps(doc, separators=(",", ":"), sort_keys=True).encode()
    js += b" " * (-len(js) % 4)
    binary += b"\x00" * (-len(binary) % 4)
    body = struct.pack("<I4s", len(js), b"JSON") + js + struct.pack("<I4s", len(binary), b"BIN\x00") + binary
    return struct.pack("<4sII", b"glTF", 2, 12 + len(body)) + body


def write(name, data):
    path = os.path.join(BAD, name)
    with open(path, "wb") as f:
        f.write(data if isinstance(data, bytes) else data.encode())


def main():
    os.makedirs(BAD, exist_ok=True)
    os.makedirs(SEEDS, exist_ok=True)
    b = triangle_bin()
    ok = base_gltf(data_uri(b))
    # A valid file (control) and the fuzzer's seed: embedded buffer and texture.
    good = base_gltf(None, image={"mimeType": "image/png", "bufferView": 4})
    del good["buffers"][0]["uri"]
    png = png_2x2()
    good["bufferViews"].append({"buffer": 0, "byteOffset": 108, "byteLength": len(png)})
    good["buffers"][0]["byteLength"] = 108 + len(png)
    seed = glb(good, b + png)
    with open(os.path.join(SEEDS, "triangle.glb"), "wb") as f:
        f.write(seed)
    write("good_triangle.gltf", json.dumps(ok, indent=1, sort_keys=True))

    cases = {
        "glb_bad_magic.glb": b"glTX" + seed[4:],
        "glb_bad_chunk_length.glb": seed[:12] + struct.pack("<I", 10**9) + seed[16:],
        "glb_json_not_json.glb": glb({"asset": 1}, b)[:20] + b"{ not json at all }" + b" " * 9,
        "glb_truncated.glb": seed[: len(seed) // 2],
        # Found by fuzzing: a declared length under 12 made the gltf crate underflow.
        "glb_length_underflow.glb": struct.pack("<4sII", b"glTF", 2, 5) + seed[12:],
        "glb_version_1.glb": struct.pack("<4sII", b"glTF", 1, len(seed)) + seed[12:],
        "gltf_missing_buffer.gltf": json.dumps(base_gltf("missing.bin")),
        "gltf_buffer_outside.gltf": json.dumps(base_gltf("../outside.bin")),
        "gltf_buffer_absolute.gltf": json.dumps(base_gltf("/etc/hostname")),
        "gltf_accessor_out_of_range.gltf": json.dumps(base_gltf(data_uri(b), index_count=400)),
        "gltf_lines.gltf": json.dumps(base_gltf(data_uri(b), mode=1)),
        "gltf_no_camera.gltf": json.dumps(base_gltf(data_uri(b), camera=False)),
        "gltf_no_mesh.gltf": json.dumps(base_gltf(data_uri(b), mesh=False)),
        "gltf_missing_texture.gltf": json.dumps(base_gltf(data_uri(b), image={"uri": "missing.png"})),
        "gltf_bad_texture.gltf": json.dumps(base_gltf(data_uri(b), image={"uri": data_uri(b"\x89PNG\r\n\x1a\nnope", "image/png")})),
        "gltf_not_json.gltf": "{ this is not json",
    }
    # Found by fuzzing: a POSITION accessor index out of range panicked inside gltf-json.
    dangling = base_gltf(data_uri(b))
    dangling["meshes"][0]["primitives"][0]["attributes"]["POSITION"] = 9
    cases["gltf_dangling_accessor.gltf"] = json.dumps(dangling)
    # Found by fuzzing: an accessor of the wrong type (VEC3 texture coordinates).
    wrong_type = base_gltf(data_uri(b), image={"uri": data_uri(png_2x2(), "image/png")})
    wrong_type["meshes"][0]["primitives"][0]["attributes"]["TEXCOORD_0"] = 1
    cases["gltf_wrong_accessor_type.gltf"] = json.dumps(wrong_type)
    # An index beyond the vertex count (a valid accessor whose values are out of range).
    bad_idx = b[:96] + struct.pack("<3I", 0, 1, 7)
    cases["gltf_index_out_of_range.gltf"] = json.dumps(base_gltf(data_uri(bad_idx)))
    for name, data in cases.items():
        write(name, data)
    print(f"wrote {len(cases) + 1} files to {BAD} and a seed to {SEEDS}")


if __name__ == "__main__":
    main()
