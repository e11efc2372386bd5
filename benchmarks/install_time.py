"""Time of ``install`` on a model, with install's disk cache empty and then filled.

  python benchmarks/install_time.py [MODEL.xml ...] [--device cpu] [--json OUT]

Each model is installed in two fresh processes that share a new, empty cache folder
(``MJX_SUPPORTFIELD_CACHE``): the first builds and proves the support fields and bakes the SDFs,
the second reads them. Kernels come from Warp's kernel cache as usual (their first build is not
install's time; see docs/performance.md). Default model: MuJoCo Warp's aloha_pot.
"""

import argparse
import json
import os
import subprocess
import sys
import tempfile

CHILD = """
import sys, time
import mujoco, mujoco_warp as mjw, warp as wp
wp.config.log_level = wp.LOG_WARNING
with wp.ScopedDevice(sys.argv[2]):
  mjm = mujoco.MjModel.from_xml_path(sys.argv[1])
  m = mjw.put_model(mjm)
  import mjx_supportfield
  mjx_supportfield.install(mjm, m)  # compiles the install kernels, if Warp's cache lacks them
  mjx_supportfield.uninstall(m)
  import shutil, os
  shutil.rmtree(os.environ["MJX_SUPPORTFIELD_CACHE"], ignore_errors=True) if sys.argv[3] == "empty" else None
  t = time.perf_counter()
  mjx_supportfield.install(mjm, m)
  wp.synchronize()
  print(time.perf_counter() - t)
"""


def aloha() -> str:
  import mujoco_warp

  return os.path.join(os.path.dirname(mujoco_warp.__file__), "test_data", "aloha_pot", "scene.xml")


def main():
  p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
  p.add_argument("models", nargs="*")
  p.add_argument("--device", default="cpu")
  p.add_argument("--json", default=None)
  args = p.parse_args()
  rows = []
  for path in args.models or [aloha()]:
    with tempfile.TemporaryDirectory(prefix="install_cache_") as cache:
      env = {**os.environ, "MJX_SUPPORTFIELD_CACHE": cache}
      times = {}
      for state in ("empty", "filled"):
        out = subprocess.run([sys.executable, "-c", CHILD, path, args.device, state], env=env, capture_output=True,
                             text=True, check=True).stdout.split()
        times[state] = float(out[-1])
    rows.append({"model": path, "device": args.device, "install_s_empty_cache": times["empty"],
                 "install_s_cached": times["filled"]})
    print(f"{os.path.basename(os.path.dirname(path)) if path.endswith('scene.xml') else os.path.basename(path)}: "
          f"install {times['empty']:.2f} s with an empty cache, {times['filled']:.2f} s cached", flush=True)
  if args.json:
    with open(args.json, "w") as f:
      json.dump({"rows": rows, "cpu_count": os.cpu_count()}, f, indent=1)


if __name__ == "__main__":
  main()
