"""Soak run: many steps of a pile through the plugin, checking the state as it goes.

  python benchmarks/soak.py [--scene benchmarks/scenes/pile_256_128.xml] [--nworld 1024]
                            [--steps 100000] [--chunk 500] [--minutes M] [--json OUT]

The worlds start from the scene's initial state (every body dropped from rest), each with a
small random velocity so they differ. Steps run ``chunk`` at a time from one captured graph
(a CUDA graph on a GPU). After every chunk the run checks, over all worlds:
  - qpos and qvel finite (a NaN anywhere is a failure);
  - total energy (MuJoCo's kinetic + potential) at most the largest initial energy plus 1 %
    of the scene's potential-energy span: a dropped pile only loses energy;
  - no overflow bit in d.overflow, no dropped broad-phase pairs.
The run stops at ``steps`` or after ``minutes`` of wall time, and the JSON says which.
"""

import argparse
import json
import os
import sys
import time

import mujoco
import mujoco_warp as mjw
import numpy as np
import warp as wp

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.dirname(HERE))
sys.path.insert(0, HERE)

import make_scenes  # noqa: E402

from mjx_supportfield import bench  # noqa: E402
from mjx_supportfield.install import get_collider  # noqa: E402
from mjx_supportfield.install import install  # noqa: E402

SPEED = 0.05  # m/s (and rad/s) of the random initial velocities


def energy(d) -> np.ndarray:
  """Per-world total energy (kinetic + potential)."""
  return d.energy.numpy().sum(axis=1)


def main():
  p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
  p.add_argument("--scene", default=os.path.join(HERE, "scenes", "pile_256_128.xml"))
  p.add_argument("--nworld", type=int, default=1024)
  p.add_argument("--steps", type=int, default=100_000)
  p.add_argument("--chunk", type=int, default=500)
  p.add_argument("--minutes", type=float, default=None, help="stop after this much wall time")
  p.add_argument("--nconmax", type=int, default=None,
                 help="contacts per world (default: 2 x MuJoCo C's after 500 steps)")
  p.add_argument("--json", default=None)
  args = p.parse_args()
  wp.config.log_level = wp.LOG_WARNING
  if not os.path.exists(args.scene):
    make_scenes.main()

  mjm = mujoco.MjModel.from_xml_path(args.scene)
  mjm.opt.enableflags |= mujoco.mjtEnableBit.mjENBL_ENERGY
  settled = bench.settled_state(mjm, 500)  # the pile mostly down: room for its contacts at rest
  nconmax = args.nconmax or 2 * settled.ncon + 16
  m = mjw.put_model(mjm)
  install(mjm, m)
  mjd = mujoco.MjData(mjm)
  mujoco.mj_forward(mjm, mjd)
  d = mjw.put_data(mjm, mjd, nworld=args.nworld, nconmax=nconmax, njmax=6 * nconmax)
  rng = np.random.default_rng(0)
  d.qvel.assign((SPEED * rng.uniform(-1, 1, size=(args.nworld, mjm.nv))).astype(np.float32))
  mjw.forward(m, d)
  e0 = energy(d)
  span = float(mjd.energy[0] - settled.energy[0])  # potential energy the pile can give up
  limit = float(e0.max()) + 0.01 * abs(span)
  collider = get_collider(m)

  def chunk():
    for _ in range(args.chunk):
      mjw.step(m, d)

  graph = None
  if wp.get_device().is_cuda:
    mjw.step(m, d)  # compile outside the capture
    with wp.ScopedCapture() as capture:
      chunk()
    graph = capture.graph
  t0 = time.perf_counter()
  steps, failures, trace = 0, [], []
  reason = "steps"
  while steps < args.steps:
    if graph is not None:
      wp.capture_launch(graph)
    else:
      chunk()
    steps += args.chunk
    qpos, qvel = d.qpos.numpy(), d.qvel.numpy()
    finite = bool(np.isfinite(qpos).all() and np.isfinite(qvel).all())
    e = energy(d)
    overflow = int(np.bitwise_or.reduce(d.overflow.numpy().ravel()))
    stats = collider.stats(d)
    row = {"step": steps, "seconds": time.perf_counter() - t0, "finite": finite, "energy_max": float(np.nanmax(e)),
           "energy_mean": float(np.nanmean(e)), "overflow_bits": overflow,
           "dropped_pairs": int(sum(stats["dropped_pairs_per_world"])), "contacts_per_world": min(int(d.nacon.numpy()[0]), d.naconmax) / args.nworld}
    trace.append(row)
    bad = []
    if not finite:
      bad.append("non-finite state")
    if row["energy_max"] > limit:
      bad.append(f"energy {row['energy_max']:.4g} > bound {limit:.4g}")
    if overflow or row["dropped_pairs"]:
      bad.append(f"overflow bits {overflow}, dropped pairs {row['dropped_pairs']}")
    if bad:
      failures.append({"step": steps, "what": bad})
    print(f"step {steps:7d}  {row['seconds']:7.1f} s  energy max {row['energy_max']:.5g} mean {row['energy_mean']:.5g}"
          f"  contacts/world {row['contacts_per_world']:.1f}  {'; '.join(bad) or 'ok'}", flush=True)
    if args.minutes and time.perf_counter() - t0 > 60 * args.minutes:
      reason = "time limit"
      break
  report = {"gpu": bench.device_name(), "scene": os.path.basename(args.scene), "nworld": args.nworld,
            "steps_run": steps, "steps_asked": args.steps, "stopped_by": reason, "chunk": args.chunk,
            "energy_initial_max": float(e0.max()), "energy_bound": limit, "failures": failures, "passed": not failures,
            "versions": {"warp": wp.__version__, "mujoco": mujoco.__version__}, "trace": trace}
  print(f"{steps} steps x {args.nworld} worlds: {'passed' if not failures else f'{len(failures)} failing chunks'}"
        f" (stopped by {reason})")
  if args.json:
    with open(args.json, "w") as f:
      json.dump(report, f, indent=1)
    print("wrote", args.json)
  sys.exit(0 if not failures else 1)


if __name__ == "__main__":
  main()
