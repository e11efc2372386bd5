"""Reduce a scene to one geom pair at one of ``compare``'s sampled states: a repro case.

  python benchmarks/reduce_pair.py MODEL GEOM1 GEOM2 OUT.xml [--state 0] [--steps 200] [--samples 5]

Writes an MJCF holding only the two geoms, each on a free body posed where its body is in MuJoCo
C's state (geom offsets and meshes as the original declares them, so the compiled geoms land
where they were), and copies their mesh files beside it under ``meshes/`` with their content's
hash in the name. Prints MuJoCo C's contacts of the pair there, which the reduced model must
reproduce (checked: its geom poses match the original's, and so do C's contacts). Licences of
copied meshes are the caller's to add.
"""

import argparse
import hashlib
import os
import shutil
import sys

import mujoco
import numpy as np

from mjx_supportfield.tools import compare


def _fmt(v) -> str:
  return " ".join(f"{float(x):.12g}" for x in v)


def _mesh_copy(spec: mujoco.MjSpec, mesh_name: str, out_dir: str) -> tuple[str, str]:
  """(file name under meshes/, scale attribute) of a mesh, its file copied with a hashed name."""
  mesh = spec.mesh(mesh_name)
  path = os.path.join(spec.modelfiledir, spec.meshdir, mesh.file)
  with open(path, "rb") as f:
    digest = hashlib.sha1(f.read()).hexdigest()
  stem, ext = os.path.splitext(os.path.basename(mesh.file))
  name = f"{stem}-{digest}{ext}"
  os.makedirs(os.path.join(out_dir, "meshes"), exist_ok=True)
  shutil.copyfile(path, os.path.join(out_dir, "meshes", name))
  return name, _fmt(mesh.scale)


def reduce_pair(path: str, names: tuple, out: str, state: int, steps: int, samples: int) -> list:
  """Writes the reduced model to ``out``; returns MuJoCo C's contacts of the pair there."""
  spec = mujoco.MjSpec.from_file(path)
  mjm = mujoco.MjModel.from_xml_path(path)
  qpos = compare.sample_states(mjm, steps, samples)[state]
  mjd = mujoco.MjData(mjm)
  mjd.qpos[:] = qpos
  mujoco.mj_forward(mjm, mjd)
  out_dir = os.path.dirname(os.path.abspath(out))
  assets, bodies = [], []
  for k, name in enumerate(names):
    g = mujoco.mj_name2id(mjm, mujoco.mjtObj.mjOBJ_GEOM, name)
    if g < 0:
      raise SystemExit(f"{path}: no geom named {name!r}")
    sg = spec.geom(name)
    body = mjm.geom_bodyid[g]
    attrs = f'name="{name}" type="{mujoco.mjtGeom(mjm.geom_type[g]).name[len("mjGEOM_"):].lower()}"'
    if mjm.geom_type[g] == mujoco.mjtGeom.mjGEOM_MESH:
      file, scale = _mesh_copy(spec, sg.meshname, out_dir)
      assets.append(f'<mesh name="{sg.meshname}" file="{file}" scale="{scale}"/>')
      attrs += f' mesh="{sg.meshname}"'
    else:
      attrs += f' size="{_fmt(mjm.geom_size[g])}"'
    attrs += f' pos="{_fmt(sg.pos)}" quat="{_fmt(sg.quat)}"'
    if mjm.geom_margin[g] or mjm.geom_gap[g]:
      attrs += f' margin="{mjm.geom_margin[g]:.12g}" gap="{mjm.geom_gap[g]:.12g}"'
    free = "<freejoint/>" if body else ""
    bodies.append(f'<body name="body{k}" pos="{_fmt(mjd.xpos[body])}" quat="{_fmt(mjd.xquat[body])}">{free}'
                  f'<geom {attrs}/></body>')
  text = (f'<mujoco model="repro_{os.path.splitext(os.path.basename(out))[0]}">\n'
          f'  <!-- {os.path.basename(path)}, state {state} of compare\'s {samples} over {steps} MuJoCo C steps: '
          f'{names[0]} and {names[1]} -->\n'
          f'  <compiler meshdir="meshes"/>\n  <asset>{"".join(assets)}</asset>\n'
          f'  <worldbody>{"".join(bodies)}</worldbody>\n</mujoco>\n')
  with open(out, "w") as f:
    f.write(text)
  return _check(mjm, mjd, names, out)


def _check(mjm, mjd, names, out) -> list:
  """The reduced model's geom poses against the original's, and MuJoCo C's contacts there."""
  small = mujoco.MjModel.from_xml_path(out)
  sd = mujoco.MjData(small)
  mujoco.mj_forward(small, sd)
  for k, name in enumerate(names):
    g = mujoco.mj_name2id(mjm, mujoco.mjtObj.mjOBJ_GEOM, name)
    if not (np.allclose(sd.geom_xpos[k], mjd.geom_xpos[g], atol=1e-6)
            and np.allclose(sd.geom_xmat[k], mjd.geom_xmat[g], atol=1e-6)):
      raise SystemExit(f"{out}: geom {name!r} does not land where it was (a frame or fromto the reducer ignores)")
  return [(np.round(c.pos, 5).tolist(), round(float(c.dist), 6), np.round(c.frame[:3], 4).tolist())
          for c in sd.contact[: sd.ncon]]


def main(argv=None) -> None:
  parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
  parser.add_argument("model")
  parser.add_argument("geom1")
  parser.add_argument("geom2")
  parser.add_argument("out")
  parser.add_argument("--state", type=int, default=0)
  parser.add_argument("--steps", type=int, default=200)
  parser.add_argument("--samples", type=int, default=5)
  args = parser.parse_args(argv)
  contacts = reduce_pair(args.model, (args.geom1, args.geom2), args.out, args.state, args.steps, args.samples)
  print(f"wrote {args.out}: MuJoCo C's contacts (pos, dist, normal):")
  for c in contacts:
    print("  ", c)


if __name__ == "__main__":
  sys.exit(main())
