"""robosuite's arms as shipped, with their hands, on a table with objects: every visual mesh kept.

  python benchmarks/robosuite_arms.py [--cache DIR] [--compare] [--json OUT]

Builds three scenes from robosuite 1.5.2's own MJCF files, unmodified: the Panda with the Panda
hand, the UR5e with the Robotiq 140 gripper (robosuite's UR5e default, the Robotiq 85, does not
load in MuJoCo 4.0: its file names two meshes 'robotiq_arg2f_base_link') and the Sawyer with the
Rethink gripper, each on a pedestal beside a table with robosuite's can, milk carton and cereal
box on it. Each starts in robosuite's home pose (the keyframe); the arms' actuators are
robosuite's torque motors, left at zero: the arm slumps from there onto the table and the
objects, which is what gives its link meshes contacts. Visual meshes (about
330 000 vertices a scene), materials and textures stay in.

robosuite's assets are about 100 MB, too large for this repository: the first run downloads
robosuite's wheel from the package index (``pip download --no-deps robosuite==1.5.2``, 157 MB)
and keeps the files the scenes use (and robosuite's licence, MIT) under the cache directory
(``$MJX_SUPPORTFIELD_CACHE`` or ``$XDG_CACHE_HOME/mjx_supportfield``, else
``~/.cache/mjx_supportfield``), then writes the scenes there. ``--compare`` runs
``mjx-supportfield compare`` on each scene (MuJoCo C against the plugin and stock MuJoCo Warp) and
exits 1 when one fails its check; benchmarks/fidelity.py takes them as scenes
``robosuite_panda``, ``robosuite_ur5e``, ``robosuite_sawyer``.
"""

import argparse
import json
import os
import subprocess
import sys
import tempfile
import zipfile

import mujoco
import numpy as np

VERSION = "1.5.2"
ASSETS = "robosuite/models/assets/"
# robot: (robosuite's robot folder, gripper file, the gripper's mesh folders)
ARMS = {
  "panda": ("panda", "panda_gripper", ("panda_gripper",)),
  "ur5e": ("ur5e", "robotiq_gripper_140", ("robotiq_140_gripper",)),
  "sawyer": ("sawyer", "rethink_gripper", ("rethink_gripper",)),
}
# robosuite's home pose of each arm (its robot classes' init_qpos), the scenes' keyframe
HOME = {
  "panda": (0.0, np.pi / 16.0, 0.0, -np.pi / 2.0 - np.pi / 3.0, 0.0, np.pi - 0.2, np.pi / 4),
  "ur5e": (-0.470, -1.735, 2.480, -2.275, -1.590, -1.991),
  "sawyer": (0.0, -1.18, 0.0, 2.18, 0.0, 0.57, -1.57),
}
OBJECTS = {"can": (-0.05, 0.0, 0.86), "milk": (0.08, 0.1, 0.9), "cereal": (0.05, -0.12, 0.9)}
OBJECT_FILES = ("meshes/can.msh", "meshes/milk.msh", "meshes/cereal.msh", "../textures/soda.png",
                "../textures/ceramic.png", "../textures/cereal.png")  # what OBJECTS' files name
TABLE_TOP = 0.8  # m
BASE = (-0.56, 0.0, 0.9)  # robosuite's arm base beside its table


def cache_dir() -> str:
  """Where the robosuite files and the scenes live (see the module docstring)."""
  root = os.environ.get("MJX_SUPPORTFIELD_CACHE") or os.path.join(
    os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache"), "mjx_supportfield")
  return os.path.join(root, f"robosuite-{VERSION}")


def _wanted(name: str) -> bool:
  """The wheel's files the scenes use: the three arms, every gripper and hand robosuite ships
  (benchmarks/compare_robots.py loads each as shipped), the objects with their meshes and
  textures, and robosuite's licence."""
  if name.endswith("/LICENSE") and ".dist-info/" in name:
    return True
  if not name.startswith(ASSETS):
    return False
  rel = name[len(ASSETS):]
  return (any(rel.startswith(f"robots/{r}/") for r, _, _ in ARMS.values())
          or rel.startswith("grippers/")
          or rel in {f"objects/{o}.xml" for o in OBJECTS}
          or rel in {os.path.normpath(os.path.join("objects", f)) for f in OBJECT_FILES})


def fetch(cache: str) -> str:
  """robosuite's asset folder under ``cache``, downloaded and unpacked on first use."""
  assets = os.path.join(cache, ASSETS)
  if os.path.isfile(os.path.join(assets, "grippers", "jaco_three_finger_gripper.xml")):
    return assets
  os.makedirs(cache, exist_ok=True)
  with tempfile.TemporaryDirectory() as tmp:
    print(f"downloading robosuite {VERSION}'s wheel (157 MB) for its assets ...", file=sys.stderr, flush=True)
    subprocess.run([sys.executable, "-m", "pip", "download", "-q", "--no-deps", f"robosuite=={VERSION}", "-d", tmp],
                   check=True)
    wheel = next(os.path.join(tmp, f) for f in os.listdir(tmp) if f.endswith(".whl"))
    with zipfile.ZipFile(wheel) as z:
      z.extractall(cache, [n for n in z.namelist() if _wanted(n)])
  return assets


def _load(path: str) -> mujoco.MjSpec:
  """A robosuite MJCF file as an MjSpec whose mesh and texture files are absolute paths, so that
  the composed scene loads from anywhere."""
  spec = mujoco.MjSpec.from_file(path)
  base = os.path.dirname(path)
  for mesh in spec.meshes:
    if mesh.file:
      mesh.file = os.path.normpath(os.path.join(base, spec.meshdir or "", mesh.file))
  for tex in spec.textures:
    if tex.file:
      tex.file = os.path.normpath(os.path.join(base, spec.texturedir or "", tex.file))
  return spec


def scene_spec(assets: str, arm: str) -> mujoco.MjSpec:
  """One arm's scene (module docstring)."""
  robot, gripper, _ = ARMS[arm]
  spec = mujoco.MjSpec()
  spec.modelname = f"robosuite_{arm}"
  spec.option.timestep = 0.002
  world = spec.worldbody
  world.add_geom(name="floor", type=mujoco.mjtGeom.mjGEOM_PLANE, size=[3, 3, 0.1])
  world.add_geom(name="table", type=mujoco.mjtGeom.mjGEOM_BOX, size=[0.4, 0.4, TABLE_TOP / 2],
                 pos=[0, 0, TABLE_TOP / 2])
  world.add_geom(name="pedestal", type=mujoco.mjtGeom.mjGEOM_BOX, size=[0.12, 0.12, BASE[2] / 2],
                 pos=[BASE[0], BASE[1], BASE[2] / 2])
  arm_spec = _load(os.path.join(assets, "robots", robot, "robot.xml"))
  hand = _load(os.path.join(assets, "grippers", f"{gripper}.xml"))
  arm_spec.body("right_hand").add_frame().attach_body(hand.worldbody.first_body(), "gripper0_", "")
  world.add_frame(pos=list(BASE)).attach_body(arm_spec.worldbody.first_body(), "robot0_", "")
  for name, pos in OBJECTS.items():
    obj = _load(os.path.join(assets, "objects", f"{name}.xml"))
    world.add_frame(pos=list(pos)).attach_body(obj.worldbody.first_body(), f"{name}_", "").add_freejoint()
  qpos = spec.compile().qpos0.copy()
  qpos[: len(HOME[arm])] = HOME[arm]  # the arm's joints come first: it is attached before the objects
  spec.add_key(name="home", qpos=qpos)
  return spec


def write_scenes(cache: str = None) -> dict:
  """Writes the three scenes into the cache (fetching robosuite first if needed); {arm: path}."""
  cache = cache or cache_dir()
  assets = fetch(cache)
  out = {}
  for arm in ARMS:
    path = os.path.join(cache, f"robosuite_{arm}.xml")
    spec = scene_spec(assets, arm)
    spec.compile()
    with open(path, "w") as f:
      f.write(spec.to_xml())
    out[arm] = path
  return out


def objects_on_table(mjm: mujoco.MjModel, mjd: mujoco.MjData, start: mujoco.MjData) -> dict:
  """The task figure of benchmarks/fidelity.py: objects still on the table."""
  on = 0
  for name in OBJECTS:
    b = mujoco.mj_name2id(mjm, mujoco.mjtObj.mjOBJ_BODY, f"{name}_object")
    x, y, z = mjd.xpos[b]
    on += abs(x) < 0.4 and abs(y) < 0.4 and z > TABLE_TOP - 0.01
  return {"objects_on_table": int(on), "objects": len(OBJECTS)}


def main(argv=None) -> int:
  parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
  parser.add_argument("--cache", default=None, help="cache directory (default: see the module docstring)")
  parser.add_argument("--compare", action="store_true", help="run mjx-supportfield compare --check on each scene")
  parser.add_argument("--json", default=None, help="with --compare: the reports, {arm: report}")
  args = parser.parse_args(argv)
  paths = write_scenes(args.cache)
  for arm, path in paths.items():
    mjm = mujoco.MjModel.from_xml_path(path)
    visual = int(((mjm.geom_contype == 0) & (mjm.geom_conaffinity == 0)).sum())
    print(f"{arm}: {path}: {mjm.ngeom} geoms ({visual} visual), {mjm.nmesh} meshes, {mjm.nmeshvert} mesh vertices")
  if not args.compare:
    return 0
  reports, failed = {}, 0
  for arm, path in paths.items():
    with tempfile.TemporaryDirectory() as tmp:
      out = os.path.join(tmp, "report.json")
      rc = subprocess.run([sys.executable, "-m", "mjx_supportfield", "compare", path, "--check", "--json", out]).returncode
      failed += rc != 0
      with open(out) as f:
        reports[arm] = json.load(f)
  if args.json:
    with open(args.json, "w") as f:
      json.dump(reports, f, indent=1)
  return 1 if failed else 0


if __name__ == "__main__":
  sys.exit(main())
