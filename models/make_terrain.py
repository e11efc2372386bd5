#!/usr/bin/env python3
"""Writes models/terrain.xml: a bumpy heightfield with one body of every convex geom type
dropped on it (deterministic; numpy only).

    python models/make_terrain.py

The heightfield is 48 x 48 samples over 0.8 m x 0.8 m (cells of 1.7 cm), bumps up to 6 cm;
each geom (3-5 cm) covers several cells.
"""

import os

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
N = 48
SIZE = (0.4, 0.4, 0.06, 0.05)  # x, y radii, elevation, base (MuJoCo's hfield size)

BODIES = [  # name, geom attributes, x, y
  ("ball", 'type="sphere" size="0.025"', -0.2, -0.2),
  ("ball2", 'type="sphere" size="0.035"', 0.0, -0.2),
  ("capsule", 'type="capsule" size="0.02 0.04" euler="90 0 30"', 0.2, -0.2),
  ("capsule2", 'type="capsule" size="0.015 0.03" euler="0 70 0"', -0.2, 0.0),
  ("box", 'type="box" size="0.04 0.03 0.02" euler="0 0 25"', 0.0, 0.0),
  ("box2", 'type="box" size="0.025 0.025 0.025" euler="30 20 0"', 0.2, 0.0),
  ("cylinder", 'type="cylinder" size="0.03 0.02"', -0.2, 0.2),
  ("ellipsoid", 'type="ellipsoid" size="0.04 0.025 0.02"', 0.0, 0.2),
  ("mesh", 'type="mesh" mesh="convex0"', 0.2, 0.2),
  ("mesh2", 'type="mesh" mesh="convex3" euler="40 0 0"', 0.1, 0.1),
]


def elevation() -> np.ndarray:
  """Samples in [0, 1]: two crossing waves and a little noise."""
  rng = np.random.default_rng(7)
  x = np.linspace(0.0, 3.0 * np.pi, N)
  z = 0.5 + 0.3 * np.sin(x)[None, :] * np.cos(0.8 * x)[:, None] + 0.1 * rng.uniform(-1, 1, size=(N, N))
  return np.clip(z, 0.0, 1.0)


def terrain_height(mjm_size, data: np.ndarray, x: float, y: float) -> float:
  """Height of the terrain surface at (x, y) in the heightfield's frame (MuJoCo's triangles)."""
  nrow, ncol = data.shape
  sx, sy, sz = mjm_size[0], mjm_size[1], mjm_size[2]
  u = (x + sx) / (2 * sx) * (ncol - 1)
  v = (y + sy) / (2 * sy) * (nrow - 1)
  c, r = min(int(u), ncol - 2), min(int(v), nrow - 2)
  fu, fv = u - c, v - r
  h00, h01, h10, h11 = data[r, c], data[r, c + 1], data[r + 1, c], data[r + 1, c + 1]
  if fv >= fu:  # triangle (r, c), (r + 1, c), (r + 1, c + 1)
    h = h00 + fv * (h10 - h00) + fu * (h11 - h10)
  else:  # triangle (r, c), (r, c + 1), (r + 1, c + 1)
    h = h00 + fu * (h01 - h00) + fv * (h11 - h01)
  return float(h * sz)


def xml() -> str:
  z = elevation()
  bodies = "".join(
    f'    <body name="{name}" pos="{x} {y} 0.12"><freejoint/><geom name="{name}" {attrs}/></body>\n'
    for name, attrs, x, y in BODIES
  )
  return (
    '<mujoco model="terrain">\n'
    '  <compiler meshdir="meshes"/>\n'
    '  <option timestep="0.002"/>\n'
    "  <asset>\n"
    f'    <hfield name="bumps" nrow="{N}" ncol="{N}" size="{" ".join(map(str, SIZE))}"\n'
    f'            elevation="{" ".join(f"{v:.4f}" for v in z.ravel())}"/>\n'
    '    <mesh name="convex0" file="convex0.obj"/>\n'
    '    <mesh name="convex3" file="convex3.obj"/>\n'
    "  </asset>\n"
    "  <worldbody>\n"
    '    <light pos="0 0 3" dir="0 0 -1"/>\n'
    '    <geom name="terrain" type="hfield" hfield="bumps"/>\n'
    f"{bodies}"
    "  </worldbody>\n"
    "</mujoco>\n"
  )


def main():
  path = os.path.join(HERE, "terrain.xml")
  with open(path, "w") as f:
    f.write(xml())
  print("wrote", path)


if __name__ == "__main__":
  main()
