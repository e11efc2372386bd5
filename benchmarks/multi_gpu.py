"""Two (or more) GPUs: one model per device, each with the plugin, stepped side by side.

  python benchmarks/multi_gpu.py [--scene benchmarks/scenes/pile_32_128.xml] [--nworld 8192]
                                 [--launches 50] [--json OUT]

Per device: ``put_model`` and ``install`` under ``wp.ScopedDevice``, a Data of ``nworld``
worlds, one step captured in a CUDA graph. Checks that every device steps on its own: with all
of MuJoCo Warp's determinism bits on, every device's contacts and qpos after 10 steps from the
same state are bitwise equal to device 0's. Then times the graph on device 0 alone and on all
devices at once (launched from one thread, synchronised at the end) and reports the aggregate
world-steps per second.
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

from mjx_supportfield import bench  # noqa: E402
from mjx_supportfield import contact_sort  # noqa: E402
from mjx_supportfield.install import install  # noqa: E402

CHECK_STEPS = 10


def setup(mjm, mjd, device, nworld: int, nconmax: int):
  """Model, Data and captured step graph on one device."""
  with wp.ScopedDevice(device):
    m = mjw.put_model(mjm)
    install(mjm, m)
    m.opt.deterministic = DeterminismType.ALL
    d = mjw.put_data(mjm, mjd, nworld=nworld, nconmax=nconmax, njmax=6 * nconmax)
    mjw.step(m, d)  # compile and make the plugin's state outside the capture
    wp.synchronize_device(device)
    with wp.ScopedCapture() as capture:
      mjw.step(m, d)
    return m, d, capture.graph


def snapshot(d, graph, device):
  """Contacts and qpos after CHECK_STEPS more graph launches (every device has run the same
  sequence of steps since its Data was made, so all should agree bit for bit)."""
  with wp.ScopedDevice(device):
    for _ in range(CHECK_STEPS):
      wp.capture_launch(graph)
    wp.synchronize_device(device)
    return contact_sort.host_contacts(d), d.qpos.numpy().copy()


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
  sims = [setup(mjm, mjd, dev, args.nworld, nconmax) for dev in devices]

  ref = snapshot(sims[0][1], sims[0][2], devices[0])
  same = []
  for dev, (_, d, g) in zip(devices[1:], sims[1:]):
    got = snapshot(d, g, dev)
    same.append(all(np.array_equal(ref[0][f], got[0][f]) for f in ref[0]) and np.array_equal(ref[1], got[1]))

  one = time_launches([(devices[0], sims[0][2])], args.launches)
  both = time_launches([(dev, s[2]) for dev, s in zip(devices, sims)], args.launches)
  single = args.nworld * args.launches / one
  aggregate = len(devices) * args.nworld * args.launches / both
  report = {"gpus": [dev.name for dev in devices], "scene": os.path.basename(args.scene), "nworld_per_gpu": args.nworld,
            "launches": args.launches, "devices_match_device0": same, "step_ms_one_gpu": one / args.launches * 1e3,
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
