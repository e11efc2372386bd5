#!/usr/bin/env python3
"""Writes the non-convex meshes (models/meshes/bowl.obj, cup.obj, torus.obj) and the scene
models/nonconvex.xml (deterministic; numpy only).

    python models/make_nonconvex.py

bowl.obj : a hemispherical shell, outer radius 8 cm, 1 cm thick, open at the top (watertight).
cup.obj  : a cylindrical cup, radius 4 cm, height 9 cm, 6 mm walls and bottom (watertight).
torus.obj: a torus, radii 5 cm and 1.5 cm (for the SDF tests).
The scene: a bowl with two balls and a small box dropped into it, and a cup with a ball inside
standing on a table; both marked non-convex with the custom text ``mjx_supportfield.nonconvex``.
"""

import os

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
MESHES = os.path.join(HERE, "meshes")
SEG = 32  # segments around the axis


def _ring(radius: float, z: float) -> np.ndarray:
  a = 2 * np.pi * np.arange(SEG) / SEG
  return np.stack([radius * np.cos(a), radius * np.sin(a), np.full(SEG, z)], axis=1)


def _band(faces: list, i0: int, i1: int, flip: bool) -> None:
  """Quads between ring i0 and ring i1 (vertex offsets), as triangles."""
  for k in range(SEG):
    a, b = i0 + k, i0 + (k + 1) % SEG
    c, d = i1 + k, i1 + (k + 1) % SEG
    tris = [(a, b, d), (a, d, c)]
    faces += [(t[0], t[2], t[1]) if flip else t for t in tris]


def _fan(faces: list, centre: int, ring: int, flip: bool) -> None:
  for k in range(SEG):
    t = (centre, ring + (k + 1) % SEG, ring + k)
    faces.append((t[0], t[2], t[1]) if flip else t)


def surface_of_revolution(profile_out, profile_in):
  """A closed shell: the outer profile (radius, z) from the bottom pole up to the rim, the inner
  one likewise; both start at a pole (radius 0)."""
  verts, faces, rings = [], [], []
  for profile in (profile_out, profile_in):
    start = len(verts)
    verts.append((0.0, 0.0, profile[0][1]))
    ids = []
    for r, z in profile[1:]:
      ids.append(len(verts))
      verts.extend(_ring(r, z))
    rings.append((start, ids))
  (po, out_rings), (pi, in_rings) = rings
  _fan(faces, po, out_rings[0], flip=False)
  for a, b in zip(out_rings, out_rings[1:]):
    _band(faces, a, b, flip=False)
  _fan(faces, pi, in_rings[0], flip=True)
  for a, b in zip(in_rings, in_rings[1:]):
    _band(faces, a, b, flip=True)
  _band(faces, out_rings[-1], in_rings[-1], flip=True)  # the rim joins the two
  return np.array(verts), np.array(faces)


def bowl(outer=0.08, thickness=0.01, rows=10):
  theta = np.linspace(0.0, np.pi / 2, rows + 1)
  prof = lambda r: [(r * np.sin(t), -r * np.cos(t)) for t in theta]  # noqa: E731
  return surface_of_revolution(prof(outer), prof(outer - thickness))


def cup(radius=0.04, height=0.09, wall=0.006):
  zs = np.linspace(0.0, height, 6)
  out = [(0.0, 0.0), (radius, 0.0)] + [(radius, z) for z in zs[1:]]
  inner = [(0.0, wall), (radius - wall, wall)] + [(radius - wall, z) for z in zs[1:]]
  return surface_of_revolution(out, inner)


def torus(big=0.05, small=0.015, n=32, m=16):
  u = 2 * np.pi * np.arange(n) / n
  v = 2 * np.pi * np.arange(m) / m
  verts = [((big + small * np.cos(b)) * np.cos(a), (big + small * np.cos(b)) * np.sin(a), small * np.sin(b))
           for a in u for b in v]
  faces = []
  for i in range(n):
    for j in range(m):
      a, b = i * m + j, ((i + 1) % n) * m + j
      c, d = i * m + (j + 1) % m, ((i + 1) % n) * m + (j + 1) % m
      faces += [(a, b, d), (a, d, c)]
  return np.array(verts), np.array(faces)


def write_obj(path, verts, faces):
  with open(path, "w") as f:
    f.write(f"# {os.path.basename(path)}: written by models/make_nonconvex.py\n")
    for v in verts:
      f.write(f"v {v[0]:.6f} {v[1]:.6f} {v[2]:.6f}\n")
    for t in faces:
      f.write(f"f {t[0] + 1} {t[1] + 1} {t[2] + 1}\n")


SCENE = """<mujoco model="nonconvex">
  <!-- A bowl and a cup collided through their own triangles (custom text below); without
       the plugin, MuJoCo uses their convex hulls and the balls rest on top. -->
  <compiler meshdir="meshes"/>
  <option timestep="0.002"/>
  <custom><text name="mjx_supportfield.nonconvex" data="bowl cup"/></custom>
  <asset>
    <mesh name="bowl" file="bowl.obj"/>
    <mesh name="cup" file="cup.obj"/>
  </asset>
  <worldbody>
    <light pos="0 0 3" dir="0 0 -1"/>
    <geom name="floor" type="plane" size="1 1 0.05"/>
    <body name="bowl" pos="0 0 0.08"><freejoint/><geom name="bowl" type="mesh" mesh="bowl" density="2000"/></body>
    <body name="ball0" pos="0.02 0.0 0.1"><freejoint/><geom name="ball0" type="sphere" size="0.015"/></body>
    <body name="ball1" pos="-0.02 0.01 0.13"><freejoint/><geom name="ball1" type="sphere" size="0.012"/></body>
    <body name="cube" pos="0.0 -0.025 0.16" euler="20 10 0"><freejoint/><geom name="cube" type="box" size="0.01 0.01 0.01"/></body>
    <geom name="table" type="box" pos="0.3 0 0.05" size="0.1 0.1 0.05"/>
    <body name="cup" pos="0.3 0 0.1"><freejoint/><geom name="cup" type="mesh" mesh="cup" density="2000"/></body>
    <body name="ball2" pos="0.3 0.0 0.23"><freejoint/><geom name="ball2" type="sphere" size="0.015"/></body>
  </worldbody>
</mujoco>
"""


def main():
  os.makedirs(MESHES, exist_ok=True)
  for name, (v, f) in {"bowl": bowl(), "cup": cup(), "torus": torus()}.items():
    write_obj(os.path.join(MESHES, f"{name}.obj"), v, f)
  with open(os.path.join(HERE, "nonconvex.xml"), "w") as f:
    f.write(SCENE)
  print("wrote meshes/bowl.obj, meshes/cup.obj, meshes/torus.obj, nonconvex.xml")


if __name__ == "__main__":
  main()
