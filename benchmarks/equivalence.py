"""Fingerprints of the plugin's physics, to show that a change meant to leave it alone does.

  python benchmarks/equivalence.py OUT.json [--steps 100] [--nworld 3] [--models PATH ...]
  python benchmarks/equivalence.py --diff BEFORE.json AFTER.json

Steps every model in ``models/`` and ``models/real/`` and the benchmark scenes (written by
make_scenes.py if missing) through ``mjw.step`` with the plugin installed, under each preset of
options below, on Warp's CPU device, and records a sha256 of the contacts (every field the
collision stage writes, the first ``nacon`` rows) and of qpos after each step, plus the last step's
contact count. Run it once on the code before a change and once after (e.g. with PYTHONPATH
pointing at a ``git worktree`` of the old commit), then ``--diff`` the two files: it prints the
first step at which any model and preset part ways and exits 1, or says they are bit-identical.

The worlds start from the model's initial state with small, seeded, different velocities, so the
worlds differ and the contacts move from step to step.
"""

import argparse
import hashlib
import json
import os
import sys

import mujoco
import mujoco_warp as mjw
import numpy as np
import warp as wp

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(HERE)
sys.path.insert(0, HERE)

import make_scenes  # noqa: E402

from mjx_supportfield.driver import install  # noqa: E402
from mjx_supportfield.driver import uninstall  # noqa: E402
from mjx_supportfield.launch.contact_sort import FIELDS  # noqa: E402
from mjx_supportfield.options import Options  # noqa: E402
from mjx_supportfield.tools.bench import settled_state  # noqa: E402

PRESETS = {
  "default": {},
  "gjk": {"narrowphase": "gjk"},
  "single_contact": {"multi_contact": False},
  "cold": {"warm_start": False, "broadphase": "nxn"},
  "field": {"support_mode": "field", "mpr_refine": 0},
}
SCENES = ("pile_32_128.xml", "primitives_32.xml", "terrain_32.xml")
SPEED = 0.05  # m/s (and rad/s) of the seeded initial velocities


def default_models() -> list[str]:
  """Every MJCF model in models/ and models/real/, and the benchmark scenes."""
  paths = []
  for folder in (os.path.join(ROOT, "models"), os.path.join(ROOT, "models", "real")):
    paths += sorted(os.path.join(folder, f) for f in os.listdir(folder) if f.endswith(".xml"))
  scenes = [os.path.join(HERE, "scenes", s) for s in SCENES]
  if not all(os.path.exists(s) for s in scenes):
    make_scenes.main()
  return paths + scenes


def digest(*arrays) -> str:
  """sha256 of the arrays' bytes, in order."""
  h = hashlib.sha256()
  for a in arrays:
    h.update(np.ascontiguousarray(a).tobytes())
  return h.hexdigest()[:16]


def contact_digest(d) -> tuple[str, int]:
  """Digest of the first nacon contacts (every field the collision stage writes) and nacon."""
  n = min(int(d.nacon.numpy()[0]), d.naconmax)
  fields = [getattr(d.contact, f).numpy()[:n] for f in FIELDS if getattr(d.contact, f).shape[0] >= n]
  return digest(*fields), n


def run(path: str, options: dict, steps: int, nworld: int) -> dict:
  """Per-step digests of one model under one preset."""
  mjm = mujoco.MjModel.from_xml_path(path)
  m = mjw.put_model(mjm)
  install(mjm, m, Options(**options))
  mjd = mujoco.MjData(mjm)
  mujoco.mj_forward(mjm, mjd)
  # room for every contact and constraint row at the start and at rest: no overflow to blur a difference
  ncon = max(mjd.ncon, settled_state(mjm, 300).ncon)
  nconmax = 2 * ncon + 32
  d = mjw.put_data(mjm, mjd, nworld=nworld, nconmax=nconmax, njmax=6 * nconmax)
  rng = np.random.default_rng(0)
  d.qvel.assign((SPEED * rng.uniform(-1, 1, size=(nworld, mjm.nv))).astype(np.float32))
  contacts, qpos = [], []
  n = 0
  for _ in range(steps):
    mjw.step(m, d)
    if d.overflow.numpy().any():
      raise RuntimeError(f"{path}: a buffer overflowed (d.overflow); fingerprints would hide what was dropped")
    c, n = contact_digest(d)
    contacts.append(c)
    qpos.append(digest(d.qpos.numpy()))
  uninstall(m)
  return {"contacts": contacts, "qpos": qpos, "nacon_last": n}


def record(out: str, models: list[str], steps: int, nworld: int) -> None:
  """Writes the digests of every model and preset to ``out``."""
  wp.config.log_level = wp.LOG_WARNING
  wp.set_device("cpu")
  report = {"steps": steps, "nworld": nworld, "runs": {}}
  for path in models:
    name = os.path.relpath(path, ROOT)
    for preset, options in PRESETS.items():
      report["runs"][f"{name} {preset}"] = run(path, options, steps, nworld)
      print(f"{name} {preset}: {report['runs'][f'{name} {preset}']['nacon_last']} contacts at the end", flush=True)
  with open(out, "w") as f:
    json.dump(report, f, indent=1)


def diff(before: str, after: str) -> int:
  """Prints where two recordings part ways; 0 when they are bit-identical."""
  with open(before) as f:
    a = json.load(f)["runs"]
  with open(after) as f:
    b = json.load(f)["runs"]
  parted = 0
  for key in sorted(set(a) | set(b)):
    if key not in a or key not in b:
      print(f"{key}: only in {'after' if key in b else 'before'}")
      parted += 1
      continue
    differs = False
    for what in ("contacts", "qpos"):
      steps = [i for i, (x, y) in enumerate(zip(a[key][what], b[key][what])) if x != y]
      if steps or len(a[key][what]) != len(b[key][what]):
        print(f"{key}: {what} differ from step {steps[0] + 1 if steps else min(len(a[key][what]), len(b[key][what]))}")
        differs = True
    parted += differs  # a run counts once, whether its contacts, its qpos or both part ways
  total = len(set(a) | set(b))
  print(f"{total - parted} of {total} model/preset runs bit-identical" if parted else
        f"all {total} model/preset runs bit-identical (contacts and qpos, every step)")
  return 1 if parted else 0


def main():
  p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
  p.add_argument("out", nargs="?", help="where to write the digests")
  p.add_argument("--steps", type=int, default=100)
  p.add_argument("--nworld", type=int, default=3)
  p.add_argument("--models", nargs="*", help="MJCF paths (default: models/, models/real/ and the benchmark scenes)")
  p.add_argument("--diff", nargs=2, metavar=("BEFORE", "AFTER"), help="compare two recordings")
  args = p.parse_args()
  if args.diff:
    sys.exit(diff(*args.diff))
  if not args.out:
    p.error("give OUT.json, or --diff BEFORE AFTER")
  record(args.out, args.models or default_models(), args.steps, args.nworld)


if __name__ == "__main__":
  main()
