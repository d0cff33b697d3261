#!/usr/bin/env python3
"""lightprobe's ring environment-map grid, written independently in Python from
the spec (docs/design.md, "The ring environment map"), to check the Rust
implementation from the outside. Used by check_mitsuba_envmap.py and bench.py.

Grid: N rings of constant polar angle theta from +Y, poles included,
D = pi/(N-1), theta_i = i*D. Pole rings hold 1 cell; ring i in between holds
n_i = 4*floor((N-1)/2 * sin(theta_i) + 0.5 + 1e-9) cells at phi_ij = 2*pi*j/n_i.
Cell = band [theta_i - D/2, theta_i + D/2] clipped to [0, pi] x sector
[phi_ij - pi/n_i, phi_ij + pi/n_i). phi = atan2(d.x, -d.z) wrapped to [0, 2pi)
(phi = 0 is -Z, pi/2 is +X). Cells are numbered ring by ring from +Y, by
increasing phi. N = 1: one cell covering the sphere.

Lat-long (Mitsuba 3 `envmap`, +Y up): column j at u = (j+0.5)/W, phi = 2*pi*u;
row i at theta = i*pi/(H-1) (first/last rows are the poles), H = W/2.

`python scripts/ring_grid.py` runs self_check() (counts, tiling, lookup).
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

# the spec's published counts for N = 2..25
SPEC_COUNTS = [2, 6, 10, 18, 26, 54, 66, 90, 106, 134, 154, 186, 210, 246, 282, 330, 370,
               422, 466, 522, 562, 622, 666, 738]


class RingGrid:
    def __init__(self, rings: int):
        if rings < 1:
            raise ValueError("rings must be >= 1")
        self.rings = N = rings
        if N == 1:
            self.delta = math.pi
            self.counts = np.array([1])
        else:
            self.delta = math.pi / (N - 1)
            c = [1]
            for i in range(1, N - 1):
                c.append(4 * math.floor((N - 1) / 2 * math.sin(i * self.delta) + 0.5 + 1e-9))
            c.append(1)
            self.counts = np.array(c, dtype=np.int64)
        self.offsets = np.concatenate([[0], np.cumsum(self.counts)])
        self.n_cells = int(self.offsets[-1])

    # -- geometry ---------------------------------------------------------
    def ring_of(self, theta: np.ndarray) -> np.ndarray:
        if self.rings == 1:
            return np.zeros(np.shape(theta), dtype=np.int64)
        i = np.floor(np.asarray(theta) / self.delta + 0.5).astype(np.int64)
        return np.clip(i, 0, self.rings - 1)

    def cell_of_angles(self, theta: np.ndarray, phi: np.ndarray) -> np.ndarray:
        """Cell index of directions given by polar angle theta (from +Y) and
        azimuth phi (any real; wrapped)."""
        theta, phi = np.broadcast_arrays(np.asarray(theta, float), np.asarray(phi, float))
        i = self.ring_of(theta)
        n = self.counts[i]
        ph = np.mod(phi, 2 * math.pi)
        j = np.floor(ph * n / (2 * math.pi) + 0.5).astype(np.int64) % n
        return self.offsets[i] + j

    def cell_of_dirs(self, d: np.ndarray) -> np.ndarray:
        d = np.asarray(d, float)
        d = d / np.linalg.norm(d, axis=-1, keepdims=True)
        theta = np.arccos(np.clip(d[..., 1], -1.0, 1.0))
        phi = np.arctan2(d[..., 0], -d[..., 2])
        return self.cell_of_angles(theta, phi)

    def cell_centre(self, c: int) -> tuple[int, int, float, float]:
        """(ring, index in ring, theta, phi) of cell c's grid point."""
        i = int(np.searchsorted(self.offsets, c, side="right") - 1)
        j = int(c - self.offsets[i])
        return i, j, i * self.delta, 2 * math.pi * j / self.counts[i]

    def cell(self, ring: int, j: int) -> int:
        return int(self.offsets[ring] + j % self.counts[ring])

    def solid_angles(self) -> np.ndarray:
        if self.rings == 1:
            return np.array([4 * math.pi])
        out = np.empty(self.n_cells)
        for i, n in enumerate(self.counts):
            t0 = max(0.0, (i - 0.5) * self.delta)
            t1 = min(math.pi, (i + 0.5) * self.delta)
            out[self.offsets[i]:self.offsets[i + 1]] = 2 * math.pi * (math.cos(t0) - math.cos(t1)) / n
        return out

    @staticmethod
    def dir_of(theta, phi) -> np.ndarray:
        """Unit direction for (theta from +Y, phi = atan2(x, -z))."""
        theta, phi = np.broadcast_arrays(np.asarray(theta, float), np.asarray(phi, float))
        s = np.sin(theta)
        return np.stack([s * np.sin(phi), np.cos(theta), -s * np.cos(phi)], -1)

    # -- lat-long ---------------------------------------------------------
    def latlong_cells(self, width: int, u_offset: float = 0.5) -> np.ndarray:
        """(H, W) cell index under each pixel centre of a Mitsuba-convention
        lat-long image (u_offset 0.5 = pixel-centred columns, as specified;
        other values only to build deliberately wrong exports)."""
        h = width // 2
        theta = np.arange(h) * math.pi / (h - 1)
        phi = 2 * math.pi * (np.arange(width) + u_offset) / width
        return self.cell_of_angles(theta[:, None], phi[None, :])

    def rasterise(self, radiance: np.ndarray, width: int, u_offset: float = 0.5) -> np.ndarray:
        """Box-filtered (point-sampled) lat-long RGB image, float32 (H, W, 3)."""
        return np.asarray(radiance, np.float32)[self.latlong_cells(width, u_offset)]


# --------------------------------------------------------------------------
# envmap.ron
# --------------------------------------------------------------------------

def f32(x) -> np.ndarray:
    return np.asarray(x, dtype=np.float32)


def write_envmap_ron(path: Path, rings: int, radiance: np.ndarray) -> None:
    """`Envmap(rings: N, radiance: [(r, g, b), ...])`, values as f32 written
    with enough digits to round-trip exactly."""
    rad = f32(radiance)
    g = RingGrid(rings)
    assert rad.shape == (g.n_cells, 3), (rad.shape, g.n_cells)
    fmt = lambda x: repr(float(x))  # noqa: E731 - float(f32) is exact; repr round-trips
    lines = [f"    ({fmt(r)}, {fmt(gg)}, {fmt(b)}),  // cell {k}" for k, (r, gg, b) in enumerate(rad)]
    Path(path).write_text(f"Envmap(\n  rings: {rings},\n  radiance: [\n" + "\n".join(lines)
                          + "\n  ],\n)\n")


def read_envmap_ron(path: Path) -> tuple[int, np.ndarray]:
    import re
    text = Path(path).read_text()
    text = re.sub(r"//[^\n]*", "", text)
    m = re.search(r"rings\s*:\s*(\d+)", text)
    rings = int(m.group(1))
    body = text[text.index("radiance"):]
    num = r"([-+0-9.eE]+|inf|NaN)"
    triples = re.findall(r"\(\s*" + num + r"\s*,\s*" + num + r"\s*,\s*" + num + r"\s*\)", body)
    return rings, f32([[float(a), float(b), float(c)] for a, b, c in triples])


def demo_envmap(rings: int, bright: list[tuple[int, int, tuple]] | None = None,
                seed: int = 7) -> np.ndarray:
    """A non-trivial sky: dim (0.05-0.15), bluer upward, a little per-cell
    variation (so a wrong cell order shows), a darker brownish ground below
    the horizon, plus `bright` cells given as (ring, index in ring, rgb)."""
    g = RingGrid(rings)
    rng = np.random.default_rng(seed)
    rad = np.zeros((g.n_cells, 3))
    for c in range(g.n_cells):
        i, j, th, ph = g.cell_centre(c)
        up = math.cos(th)                       # +1 zenith .. -1 nadir
        if up >= -1e-9:
            base = np.array([0.07, 0.09, 0.11]) + up * np.array([0.01, 0.025, 0.05])
        else:
            base = np.array([0.065, 0.055, 0.045]) + up * np.array([0.015, 0.015, 0.015])
        rad[c] = base * (1 + 0.15 * rng.uniform(-1, 1))
    for ring, j, rgb in bright or []:
        rad[g.cell(ring, j)] = rgb
    return f32(rad)


def self_check() -> None:
    for n, want in zip(range(2, 26), SPEC_COUNTS):
        g = RingGrid(n)
        assert g.n_cells == want, (n, g.n_cells, want)
        assert abs(g.solid_angles().sum() - 4 * math.pi) < 1e-9
    assert RingGrid(1).n_cells == 1
    # every cell's own centre direction maps back to it (ring 0 / N-1 too)
    for n in (2, 3, 9, 21):
        g = RingGrid(n)
        for c in range(g.n_cells):
            _, _, th, ph = g.cell_centre(c)
            assert int(g.cell_of_dirs(g.dir_of(th, ph))) == c, (n, c)
    # uniform directions land in cells in proportion to solid angle
    g = RingGrid(9)
    rng = np.random.default_rng(0)
    v = rng.normal(size=(400_000, 3))
    hist = np.bincount(g.cell_of_dirs(v), minlength=g.n_cells) / len(v)
    expect = g.solid_angles() / (4 * math.pi)
    sd = np.sqrt(expect * (1 - expect) / len(v))
    assert np.all(np.abs(hist - expect) < 6 * sd + 1e-12), np.max(np.abs(hist - expect) / sd)
    # azimuth convention: phi = 0 is -Z, phi = pi/2 is +X
    assert int(g.cell_of_dirs(np.array([0.0, 0.0, -1.0]))) == g.cell(4, 0)
    assert int(g.cell_of_dirs(np.array([1.0, 0.0, 0.0]))) == g.cell(4, g.counts[4] // 4)


if __name__ == "__main__":
    self_check()
    for n in (9, 21):
        g = RingGrid(n)
        print(f"{n} rings: {g.n_cells} cells, per ring {g.counts.tolist()}")
    print("ring_grid self-check OK")
