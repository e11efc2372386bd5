"""Two (or more) GPUs: one model per device, each with the plugin, stepped side by side.

  python benchmarks/multi_gpu.py [--scene benchmarks/scenes/pile_32_128.xml] [--nworld 8192]
                                 [--check-nworld 256] [--launches 50] [--json OUT]

Per device: ``put_model`` and ``install`` under ``wp.ScopedDevice``. First a check that every
device collides and steps on its own, from the same state in ``--check-nworld`` worlds: the
plugin's contacts of one collision call, sorted (DeterminismType.CONTACTS), are bitwise equal
to device 0's; qpos after 10 steps, with the contact and constraint orders fixed (CONTACTS |
CONSTRAINT), differs from device 0's by at most twice what two runs on device 0 differ by (not
ATOMICS: its order-invariant reductions need Warp's deterministic launches, whose scratch
buffers outgrow 2^31 entries on this scene, so the solver's float atomics make runs differ a
little on any one device). Then a Data of ``--nworld`` worlds per device, one step
captured in a CUDA graph, timed on device 0 alone and on all devices at once (launched from
one thread, synchronised at the end): the aggregate world-steps per second.
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
from mujoco_warp._src.types import DeterminismType

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.dirname(HERE))
sys.path.insert(0, HERE)

import make_scenes  # noqa: E402

from mjx_supportfield.driver import collision  # noqa: E402
from mjx_supportfield.driver import install  # noqa: E402
from mjx_supportfield.launch import contact_sort  # noqa: E402
from mjx_supportfield.tools import bench  # noqa: E402

CHECK_STEPS = 10


def check(mjm, mjd, device, nworld: int, nconmax: int):
  """Sorted contacts of one plugin collision call, and qpos after CHECK_STEPS steps, on one device."""
  with wp.ScopedDevice(device):
    m = mjw.put_model(mjm)
    install(mjm, m)
    m.opt.deterministic = DeterminismType.CONTACTS | DeterminismType.CONSTRAINT
    d = mjw.put_data(mjm, mjd, nworld=nworld, nconmax=nconmax, njmax=6 * nconmax)
    mjw.kinematics(m, d)
    collision(m, d)
    contacts = contact_sort.host_contacts(d)
    for _ in range(CHECK_STEPS):
      mjw.step(m, d)
    wp.synchronize_device(device)
    return contacts, d.qpos.numpy().copy()


def setup(mjm, mjd, device, nworld: int, nconmax: int):
  """Model, Data and captured step graph on one device."""
  with wp.ScopedDevice(device):
    m = mjw.put_model(mjm)
    install(mjm, m)
    d = mjw.put_data(mjm, mjd, nworld=nworld, nconmax=nconmax, njmax=6 * nconmax)
    mjw.step(m, d)  # compile and make the plugin's state outside the capture
    wp.synchronize_device(device)
    with wp.ScopedCapture() as capture:
      mjw.step(m, d)
    return m, d, capture.graph


def time_launches(runs, launches: int) -> float:
  """Seconds for ``launches`` graph launches on each (device, graph) in ``runs``, interleaved."""
  for dev, g in runs:
    wp.capture_launch(g, stream=dev.stream)
  wp.synchronize()
  t = time.perf_counter()
  for _ in range(launches):
    for dev, g in runs:
      wp.capture_launch(g, stream=dev.stream)
  wp.synchronize()
  return time.perf_counter() - t


def main():
  p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
  p.add_argument("--scene", default=os.path.join(HERE, "scenes", "pile_32_128.xml"))
  p.add_argument("--nworld", type=int, default=8192)
  p.add_argument("--check-nworld", type=int, default=256)
  p.add_argument("--launches", type=int, default=50)
  p.add_argument("--json", default=None)
  args = p.parse_args()
  wp.config.log_level = wp.LOG_WARNING
  devices = wp.get_cuda_devices()
  if len(devices) < 2:
    sys.exit(f"multi_gpu: needs 2 or more CUDA devices, found {len(devices)}")
  if not os.path.exists(args.scene):
    make_scenes.main()
  mjm = mujoco.MjModel.from_xml_path(args.scene)
  mjd = bench.settled_state(mjm, 200)
  nconmax = int(1.5 * mjd.ncon) + 16
  ref = check(mjm, mjd, devices[0], args.check_nworld, nconmax)
  run_to_run = float(np.max(np.abs(ref[1] - check(mjm, mjd, devices[0], args.check_nworld, nconmax)[1])))
  agreement = []
  for dev in devices[1:]:
    contacts, qpos = check(mjm, mjd, dev, args.check_nworld, nconmax)
    agreement.append({
      "device": dev.alias,
      "contacts": len(contacts["dist"]),
      "contacts_bitwise_equal": all(np.array_equal(ref[0][f], contacts[f]) for f in ref[0]),
      "qpos_bitwise_equal": bool(np.array_equal(ref[1], qpos)),
      "qpos_max_abs_diff": float(np.max(np.abs(ref[1] - qpos))),
    })
  same = [a["contacts"] > 0 and a["contacts_bitwise_equal"] and a["qpos_max_abs_diff"] <= 2.0 * run_to_run + 1e-6
          for a in agreement]
  sims = [setup(mjm, mjd, dev, args.nworld, nconmax) for dev in devices]

  one = time_launches([(devices[0], sims[0][2])], args.launches)
  both = time_launches([(dev, s[2]) for dev, s in zip(devices, sims)], args.launches)
  single = args.nworld * args.launches / one
  aggregate = len(devices) * args.nworld * args.launches / both
  report = {"gpus": [dev.name for dev in devices], "scene": os.path.basename(args.scene), "nworld_per_gpu": args.nworld,
            "launches": args.launches, "check_nworld": args.check_nworld, "qpos_run_to_run_device0": run_to_run,
            "agreement_with_device0": agreement,
            "devices_match_device0": same, "step_ms_one_gpu": one / args.launches * 1e3,
            "step_ms_all_gpus": both / args.launches * 1e3, "world_steps_per_s_one_gpu": single,
            "world_steps_per_s_all_gpus": aggregate, "scaling": aggregate / single,
            "versions": {"warp": wp.__version__, "mujoco": mujoco.__version__}}
  print(json.dumps(report, indent=1))
  if args.json:
    with open(args.json, "w") as f:
      json.dump(report, f, indent=1)
  sys.exit(0 if all(same) else 1)


if __name__ == "__main__":
  main()
