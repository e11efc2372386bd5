"""Run-to-run determinism on the GPU, plugin and stock MuJoCo Warp, with and without CUDA graphs.

  python benchmarks/determinism.py [--scene models/convex_pile.xml] [--nworld 64] [--steps 20]
                                   [--json OUT]

With all of MuJoCo Warp's determinism bits set (``m.opt.deterministic = DeterminismType.ALL``),
each implementation steps the scene ``steps`` times from a reset, four times: twice uncaptured
and twice by replaying one captured step. For every pair of runs the report gives the first step
at which
  - the contacts differ in order or bits (every field the collision stage writes),
  - the contacts differ as a set (rows sorted, so order does not count),
  - qpos differs, and by how much at the end.
Stock MuJoCo Warp 4.0 does not sort its contacts, so its contact order may differ; the plugin
sorts when the CONTACTS bit is set (contact_sort.py).
"""

import argparse
import json
import os

import mujoco
import mujoco_warp as mjw
import numpy as np
import warp as wp
from mujoco_warp._src.types import DeterminismType

from mjx_supportfield.driver import install
from mjx_supportfield.launch import contact_sort

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def as_set(c: dict) -> np.ndarray:
  """The contacts as rows of raw bytes, sorted: equal when the same contacts come in any order."""
  n = len(c["dist"])
  rows = np.concatenate([np.ascontiguousarray(v).reshape(n, -1).view(np.uint8).reshape(n, -1) for v in c.values()],
                        axis=1)
  return rows[np.lexsort(rows.T[::-1])] if n else rows


def run(m, d, steps: int, graph=None) -> list:
  """Steps from a reset; per step the contacts and qpos."""
  mjw.reset_data(m, d)
  out = []
  for _ in range(steps):
    if graph is None:
      mjw.step(m, d)
    else:
      wp.capture_launch(graph)
    wp.synchronize()
    out.append((contact_sort.host_contacts(d), d.qpos.numpy().copy()))
  return out


def compare(a: list, b: list) -> dict:
  """First steps where two runs differ (None: never), and the final qpos difference."""

  def first(pred):
    return next((k for k, (x, y) in enumerate(zip(a, b)) if pred(x, y)), None)

  return {
    "first_step_contacts_differ": first(lambda x, y: x[0].keys() != y[0].keys()
                                        or any(not np.array_equal(x[0][f], y[0][f]) for f in x[0])),
    "first_step_contact_sets_differ": first(lambda x, y: not np.array_equal(as_set(x[0]), as_set(y[0]))),
    "first_step_qpos_differs": first(lambda x, y: not np.array_equal(x[1], y[1])),
    "final_qpos_max_abs_diff": float(np.abs(a[-1][1] - b[-1][1]).max()),
  }


def check(path: str, nworld: int, steps: int, plugin: bool) -> dict:
  """The four runs of one implementation and their comparisons."""
  mjm = mujoco.MjModel.from_xml_path(path)
  m = mjw.put_model(mjm)
  if plugin:
    install(mjm, m)
  m.opt.deterministic = DeterminismType.ALL
  d = mjw.make_data(mjm, nworld=nworld)
  mjw.step(m, d)  # compiles, and makes the plugin's per-Data state outside the capture
  wp.synchronize()
  with wp.ScopedCapture() as capture:
    mjw.step(m, d)
  runs = {"uncaptured_1": run(m, d, steps), "uncaptured_2": run(m, d, steps),
          "graph_1": run(m, d, steps, capture.graph), "graph_2": run(m, d, steps, capture.graph)}
  pairs = [("uncaptured_1", "uncaptured_2"), ("graph_1", "graph_2"), ("uncaptured_1", "graph_1")]
  return {"contacts_per_world": len(runs["uncaptured_1"][-1][0]["dist"]) / nworld,
          **{f"{x} vs {y}": compare(runs[x], runs[y]) for x, y in pairs}}


def main():
  p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
  p.add_argument("--scene", default=os.path.join(ROOT, "models", "convex_pile.xml"))
  p.add_argument("--nworld", type=int, default=64)
  p.add_argument("--steps", type=int, default=20)
  p.add_argument("--json", default=None)
  args = p.parse_args()
  wp.config.log_level = wp.LOG_WARNING
  device = wp.get_device()
  report = {"device": device.name if device.is_cuda else "cpu", "scene": os.path.basename(args.scene),
            "nworld": args.nworld, "steps": args.steps,
            "versions": {"warp": wp.__version__, "mujoco": mujoco.__version__}}
  for impl in ("stock", "plugin"):
    report[impl] = check(args.scene, args.nworld, args.steps, impl == "plugin")
    print(impl, json.dumps(report[impl], indent=1), flush=True)
  if args.json:
    with open(args.json, "w") as f:
      json.dump(report, f, indent=1)
    print("wrote", args.json)


if __name__ == "__main__":
  main()
