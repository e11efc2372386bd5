#!/usr/bin/env python3
"""Generate the small convex meshes used by the test scenes in models/.

Deterministic (fixed numpy seed, numpy only).  Run from anywhere, e.g.

    python models/make_meshes.py

Writes Wavefront OBJ files into models/meshes/ (next to this script):

    convex0.obj .. convex5.obj   random convex point clouds (hull vertices only,
                                 outward-oriented triangle faces)
    box.obj                      the 8 corners of a 0.1 m cube (half-size 0.05)
    cylinder.obj                 16-segment prism, radius 0.03, half-height 0.04

Coordinates are in metres, written with 6 decimals, and centred near the
origin.  Re-running the script rewrites byte-identical files.
"""

from __future__ import annotations

import itertools
import os

import numpy as np

SEED = 20240521
OUT_DIR = os.path.join(os.path.dirname(os.path.abspath(__file__)), "meshes")
DECIMALS = 6

# (name, number of sampled points, ellipsoid semi-axes in metres)
# Shapes: round, flat, elongated, and a few in between.
CLOUDS = [
    ("convex0", 32, (0.030, 0.030, 0.028)),  # round
    ("convex1", 40, (0.045, 0.038, 0.012)),  # flat (disc / lentil)
    ("convex2", 36, (0.060, 0.018, 0.020)),  # elongated (cigar)
    ("convex3", 24, (0.035, 0.026, 0.022)),  # coarse, few points
    ("convex4", 48, (0.040, 0.030, 0.016)),  # flattish, finer
    ("convex5", 28, (0.022, 0.028, 0.040)),  # elongated along z
]

BOX_HALF = 0.05
CYL_RADIUS = 0.03
CYL_HALF_HEIGHT = 0.04
CYL_SEGMENTS = 16


def random_rotation(rng: np.random.Generator) -> np.ndarray:
    """Uniform random rotation matrix (via a random unit quaternion)."""
    q = rng.normal(size=4)
    q /= np.linalg.norm(q)
    w, x, y, z = q
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
    )


def sample_cloud(rng: np.random.Generator, n: int, axes) -> np.ndarray:
    """n points on (~75%) or inside (~25%) an ellipsoid, randomly rotated."""
    d = rng.normal(size=(n, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    r = np.ones(n)
    inside = rng.random(n) < 0.25
    r[inside] = rng.uniform(0.3, 0.95, size=inside.sum())
    pts = d * r[:, None] * np.asarray(axes)[None, :]
    # random rotation so the principal axes are not aligned with x/y/z
    pts = pts @ random_rotation(rng).T
    pts -= pts.mean(axis=0)
    return pts


def convex_hull(points: np.ndarray):
    """Brute-force 3D hull for small point sets in general position.

    Returns (vertices, faces): only the hull vertices (in original order) and
    outward-oriented triangles indexing into them.
    """
    p = np.asarray(points, dtype=np.float64)
    n = len(p)
    scale = np.abs(p).max()
    eps = 1e-9 * scale**3
    faces = []
    for i, j, k in itertools.combinations(range(n), 3):
        nrm = np.cross(p[j] - p[i], p[k] - p[i])
        if np.linalg.norm(nrm) < 1e-12 * scale**2:
            continue
        d = (p - p[i]) @ nrm
        d[[i, j, k]] = 0.0
        if np.all(d <= eps):
            faces.append((i, j, k))
        elif np.all(d >= -eps):
            faces.append((i, k, j))
    used = sorted({v for f in faces for v in f})
    remap = {old: new for new, old in enumerate(used)}
    verts = p[used]
    faces = [tuple(remap[v] for v in f) for f in faces]
    # closed triangulated sphere: F = 2V - 4 (fails if points were degenerate)
    assert len(faces) == 2 * len(verts) - 4, (len(faces), len(verts))
    return verts, faces


def box_mesh(h: float):
    v = np.array(list(itertools.product((-h, h), repeat=3)))  # index = 4x+2y+z
    faces = [
        (0, 1, 3), (0, 3, 2),  # -x
        (4, 6, 7), (4, 7, 5),  # +x
        (0, 4, 5), (0, 5, 1),  # -y
        (2, 3, 7), (2, 7, 6),  # +y
        (0, 2, 6), (0, 6, 4),  # -z
        (1, 5, 7), (1, 7, 3),  # +z
    ]
    return v, faces


def cylinder_mesh(r: float, h: float, nseg: int):
    # offset by half a segment so there are flat side faces facing +-x and +-y
    ang = (np.arange(nseg) + 0.5) * 2 * np.pi / nseg
    ring = np.stack([r * np.cos(ang), r * np.sin(ang)], axis=1)
    bot = np.column_stack([ring, np.full(nseg, -h)])
    top = np.column_stack([ring, np.full(nseg, h)])
    v = np.vstack([bot, top])  # bottom: 0..n-1, top: n..2n-1
    faces = []
    for k in range(nseg):
        a, b = k, (k + 1) % nseg
        faces.append((a, b, nseg + b))
        faces.append((a, nseg + b, nseg + a))
    for k in range(1, nseg - 1):  # caps as triangle fans
        faces.append((0, k + 1, k))  # bottom, normal -z
        faces.append((nseg, nseg + k, nseg + k + 1))  # top, normal +z
    return v, faces


def check_outward(v: np.ndarray, faces) -> None:
    c = v.mean(axis=0)
    for f in faces:
        a, b, cc = v[list(f)]
        nrm = np.cross(b - a, cc - a)
        assert np.dot(nrm, a - c) > 0, f"inward face {f}"


def write_obj(path: str, v: np.ndarray, faces, comment: str) -> None:
    lines = [f"# {comment}", f"# {len(v)} vertices, {len(faces)} faces"]
    for x in v:
        lines.append("v " + " ".join(f"{c:.{DECIMALS}f}" for c in x))
    for f in faces:
        lines.append("f " + " ".join(str(i + 1) for i in f))
    with open(path, "w", newline="\n") as fh:
        fh.write("\n".join(lines) + "\n")


def main() -> None:
    os.makedirs(OUT_DIR, exist_ok=True)
    rng = np.random.default_rng(SEED)
    total = 0
    for name, n, axes in CLOUDS:
        pts = np.round(sample_cloud(rng, n, axes), DECIMALS)
        v, f = convex_hull(pts)
        check_outward(v, f)
        write_obj(
            os.path.join(OUT_DIR, name + ".obj"), v, f,
            f"{name}: hull of {n} random points in ellipsoid axes {axes} "
            f"(make_meshes.py, seed {SEED})",
        )
        total += len(v)
        print(f"{name}.obj: {n} points -> {len(v)} hull vertices, {len(f)} faces, "
              f"z range [{v[:, 2].min():.4f}, {v[:, 2].max():.4f}]")

    v, f = box_mesh(BOX_HALF)
    check_outward(v, f)
    write_obj(os.path.join(OUT_DIR, "box.obj"), v, f,
              f"box: cube with half-size {BOX_HALF} (make_meshes.py)")
    total += len(v)
    print(f"box.obj: {len(v)} vertices, {len(f)} faces")

    v, f = cylinder_mesh(CYL_RADIUS, CYL_HALF_HEIGHT, CYL_SEGMENTS)
    v = np.round(v, DECIMALS)
    check_outward(v, f)
    write_obj(os.path.join(OUT_DIR, "cylinder.obj"), v, f,
              f"cylinder: {CYL_SEGMENTS}-segment prism, radius {CYL_RADIUS}, "
              f"half-height {CYL_HALF_HEIGHT}, axis z (make_meshes.py)")
    total += len(v)
    print(f"cylinder.obj: {len(v)} vertices, {len(f)} faces")
    print(f"total vertices: {total}")


if __name__ == "__main__":
    main()
