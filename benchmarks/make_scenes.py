"""Writes the benchmark scenes into benchmarks/scenes/ (deterministic: fixed seeds).

  python benchmarks/make_scenes.py

pile_<n>_<p>.xml : n random convex meshes (p points each, on random ellipsoids) dropped in a
                   loose lattice onto a plane; they settle into a pile.
primitives_<n>.xml: n mixed primitives (sphere, capsule, box, cylinder, ellipsoid) likewise.
primitives_layers_<n>.xml: n mixed primitives dropped in three layers onto each other: a pile that
                   rests on itself, most contacts between primitives.
terrain_<n>.xml  : n mixed primitives and convex meshes dropped on a bumpy 64 x 64 heightfield.
cost_<class>.xml : 48 geoms in three layers whose contacts are of one pair class (analytic, primitive,
                   mesh, mesh_mesh): benchmarks/cost_model.py's scenes.
"""

import os

import numpy as np

HERE = os.path.join(os.path.dirname(os.path.abspath(__file__)), "scenes")
HEADER = '<mujoco model="{name}">\n  <option timestep="0.002"/>\n'
FLOOR = '    <geom name="floor" type="plane" size="0 0 0.05"/>\n    <light pos="0 0 3" dir="0 0 -1"/>\n'


def _lattice(n: int, spacing: float, z0: float):
  side = int(np.ceil(np.sqrt(n / 2)))
  for k in range(n):
    layer, r = divmod(k, side * side)
    i, j = divmod(r, side)
    yield (i - side / 2) * spacing, (j - side / 2) * spacing, z0 + layer * spacing


def ellipsoid_points(rng, npoints: int) -> np.ndarray:
  axes = rng.uniform(0.02, 0.05, size=3)
  p = rng.normal(size=(npoints, 3))
  p = p / np.linalg.norm(p, axis=1, keepdims=True) * axes
  q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
  return p @ q.T


def pile(n: int, npoints: int, seed: int = 0) -> str:
  rng = np.random.default_rng(seed)
  name = f"pile_{n}_{npoints}"
  assets = "".join(
    f'    <mesh name="m{k}" vertex="{" ".join(f"{x:.5f}" for x in ellipsoid_points(rng, npoints).ravel())}"/>\n'
    for k in range(n)
  )
  bodies = "".join(
    f'    <body name="b{k}" pos="{x:.3f} {y:.3f} {z:.3f}"><freejoint/><geom name="g{k}" type="mesh" mesh="m{k}"/></body>\n'
    for k, (x, y, z) in enumerate(_lattice(n, 0.11, 0.06))
  )
  return HEADER.format(name=name) + f"  <asset>\n{assets}  </asset>\n  <worldbody>\n{FLOOR}{bodies}  </worldbody>\n</mujoco>\n"


def primitives(n: int, seed: int = 0) -> str:
  rng = np.random.default_rng(seed)
  kinds = ["sphere", "capsule", "box", "cylinder", "ellipsoid"]
  bodies = []
  for k, (x, y, z) in enumerate(_lattice(n, 0.11, 0.06)):
    kind = kinds[k % len(kinds)]
    s = rng.uniform(0.02, 0.04, size=3)
    size = {"sphere": f"{s[0]:.3f}", "capsule": f"{s[0]:.3f} {s[1]:.3f}", "box": f"{s[0]:.3f} {s[1]:.3f} {s[2]:.3f}",
            "cylinder": f"{s[0]:.3f} {s[1]:.3f}", "ellipsoid": f"{s[0]:.3f} {s[1]:.3f} {s[2]:.3f}"}[kind]
    bodies.append(f'    <body name="b{k}" pos="{x:.3f} {y:.3f} {z:.3f}"><freejoint/>'
                  f'<geom name="g{k}" type="{kind}" size="{size}"/></body>\n')
  return HEADER.format(name=f"primitives_{n}") + f"  <worldbody>\n{FLOOR}{''.join(bodies)}  </worldbody>\n</mujoco>\n"


PRIMITIVE_KINDS = ("sphere", "capsule", "box", "cylinder", "ellipsoid")
# the kinds that make each pair class of Options.stock_pair_classes carry a stack's contacts
CLASS_KINDS = {
  "analytic": ("sphere", "capsule", "box"),
  "primitive": ("cylinder", "ellipsoid"),
  "mesh": ("mesh", "box", "capsule", "sphere"),  # a checkerboard of meshes and primitives
  "mesh_mesh": ("mesh",),
}


def layers(side: int, nlayer: int, seed: int = 0, kinds: tuple = PRIMITIVE_KINDS, name: str = "") -> str:
  """Geoms of ``kinds`` (primitives, or "mesh": a random hull) dropped in ``nlayer`` layers of
  ``side`` x ``side``, each layer shifted by half a cell so that its bodies land on the ones below:
  a pile that rests on itself, not only on the floor (most pairs geom against geom, many of them
  stacked)."""
  rng = np.random.default_rng(seed)
  spacing = 0.085
  bodies, meshes = [], []
  for layer in range(nlayer):
    shift = 0.5 * spacing * (layer % 2)
    for i in range(side):
      for j in range(side):
        k = len(bodies)
        kind = kinds[k % len(kinds)]
        if "mesh" in kinds and len(kinds) > 1:  # each mesh among primitives, each primitive among meshes
          kind = "mesh" if (i + j + layer) % 2 == 0 else kinds[1 + k % (len(kinds) - 1)]
        s = rng.uniform(0.02, 0.04, size=3)
        if kind == "mesh":
          meshes.append(f'    <mesh name="m{k}" vertex="{" ".join(f"{v:.5f}" for v in ellipsoid_points(rng, 64).ravel())}"/>\n')
          attrs = f'type="mesh" mesh="m{k}"'
        else:
          size = {"sphere": f"{s[0]:.3f}", "capsule": f"{s[0]:.3f} {s[1]:.3f}",
                  "box": f"{s[0]:.3f} {s[1]:.3f} {s[2]:.3f}", "cylinder": f"{s[0]:.3f} {s[1]:.3f}",
                  "ellipsoid": f"{s[0]:.3f} {s[1]:.3f} {s[2]:.3f}"}[kind]
          attrs = f'type="{kind}" size="{size}"'
        x, y, z = (i - side / 2) * spacing + shift, (j - side / 2) * spacing + shift, 0.06 + layer * 0.1
        bodies.append(f'    <body name="b{k}" pos="{x:.3f} {y:.3f} {z:.3f}"><freejoint/>'
                      f'<geom name="g{k}" {attrs}/></body>\n')
  name = name or f"primitives_layers_{side * side * nlayer}"
  assets = f"  <asset>\n{''.join(meshes)}  </asset>\n" if meshes else ""
  return HEADER.format(name=name) + assets + f"  <worldbody>\n{FLOOR}{''.join(bodies)}  </worldbody>\n</mujoco>\n"


# the kinds dropped on bumps for each heightfield pair class
HFIELD_CLASS_KINDS = {
  "hfield_round": ("sphere", "capsule"),
  "hfield_prism": ("box", "cylinder", "ellipsoid", "mesh"),
}
TERRAIN_KINDS = ("sphere", "capsule", "box", "cylinder", "ellipsoid", "mesh")


def class_scenes() -> dict:
  """A scene a pair class, for the cost model (cost_model.py): cost_<class>.xml, a stack of 48
  geoms (CLASS_KINDS), or for the heightfield classes 32 geoms dropped on bumps (HFIELD_CLASS_KINDS)."""
  scenes = {f"cost_{c}.xml": layers(4, 3, seed=1, kinds=kinds, name=f"cost_{c}") for c, kinds in CLASS_KINDS.items()}
  scenes.update({f"cost_{c}.xml": terrain(32, seed=1, kinds=kinds, name=f"cost_{c}")
                 for c, kinds in HFIELD_CLASS_KINDS.items()})
  return scenes


def terrain(n: int, seed: int = 0, kinds: tuple = TERRAIN_KINDS, name: str = "") -> str:
  rng = np.random.default_rng(seed)
  nrow = ncol = 64
  x = np.linspace(0, 4 * np.pi, ncol)
  bumps = 0.5 + 0.25 * np.sin(x)[None, :] * np.cos(0.7 * x)[:, None] + 0.25 * rng.uniform(size=(nrow, ncol))
  elevation = " ".join(f"{v:.3f}" for v in bumps.ravel())
  meshes = "".join(
    f'    <mesh name="m{k}" vertex="{" ".join(f"{v:.5f}" for v in ellipsoid_points(rng, 64).ravel())}"/>\n'
    for k in range(n // 6 + 1)
  )
  bodies = []
  for k, (x0, y0, z0) in enumerate(_lattice(n, 0.15, 0.25)):
    kind = kinds[k % len(kinds)]
    s = rng.uniform(0.02, 0.04, size=3)
    attrs = {"sphere": f'size="{s[0]:.3f}"', "capsule": f'size="{s[0]:.3f} {s[1]:.3f}"',
             "box": f'size="{s[0]:.3f} {s[1]:.3f} {s[2]:.3f}"', "cylinder": f'size="{s[0]:.3f} {s[1]:.3f}"',
             "ellipsoid": f'size="{s[0]:.3f} {s[1]:.3f} {s[2]:.3f}"', "mesh": f'mesh="m{k // 6}"'}[kind]
    bodies.append(f'    <body name="b{k}" pos="{x0:.3f} {y0:.3f} {z0:.3f}"><freejoint/>'
                  f'<geom name="g{k}" type="{kind}" {attrs}/></body>\n')
  meshes = meshes if "mesh" in kinds else ""  # made all the same: the bodies' sizes draw after them
  return (HEADER.format(name=name or f"terrain_{n}") + '  <asset>\n    <hfield name="bumps" '
          f'nrow="{nrow}" ncol="{ncol}" size="1.5 1.5 0.1 0.05" elevation="{elevation}"/>\n{meshes}  </asset>\n'
          '  <worldbody>\n'
          '    <geom name="terrain" type="hfield" hfield="bumps"/>\n    <light pos="0 0 3" dir="0 0 -1"/>\n'
          f"{''.join(bodies)}  </worldbody>\n</mujoco>\n")


def main():
  os.makedirs(HERE, exist_ok=True)
  scenes = {"pile_32_128.xml": pile(32, 128), "pile_256_128.xml": pile(256, 128), "pile_1024_128.xml": pile(1024, 128),
            "pile_32_1024.xml": pile(32, 1024), "primitives_32.xml": primitives(32),
            "primitives_layers_48.xml": layers(4, 3),
            "terrain_32.xml": terrain(32), **class_scenes()}
  for fname, xml in scenes.items():
    with open(os.path.join(HERE, fname), "w") as f:
      f.write(xml)
    print("wrote", os.path.join(HERE, fname))


if __name__ == "__main__":
  main()
