"""A model's first step with the plugin, from an empty kernel cache, split into what compiles.

  python benchmarks/first_step.py [MODEL.xml ...] [--device cpu|cuda:0] [--nworld 64] [--json OUT]
                                  [--keep-mujoco-warp] [--base-cache DIR] [--no-prebuilt]

Each model runs in a fresh process whose Warp kernel cache (``WARP_CACHE_PATH``) and install's
disk cache start empty: load, ``mjw.put_model``, ``install``, ``mjw.make_data``, one ``mjw.step``.
The plugin's compile notes (launch/first_use.py, ``compile_history``) split the time: install's
kernels, MuJoCo Warp's own modules (paid without the plugin too) and the plugin's first collision.
``--keep-mujoco-warp`` first fills the cache with MuJoCo Warp's modules alone (a step of the model
without the plugin, in another process), so that only the plugin's compile; ``--base-cache DIR``
starts from a copy of kernel cache DIR (``~/.cache/warp``) less the plugin's modules instead.
The plugin's modules found in a pack of prebuilt binaries (launch/prebuilt.py) load from it
instead of compiling; ``--no-prebuilt`` ignores the packs, to time a build from source.
Default models: the suite's 32-mesh pile, models/terrain.xml and quadruped_rough.
"""

import argparse
import json
import os
import shutil
import subprocess
import sys
import tempfile

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(HERE)

CHILD = """
import json, sys, time
t0 = time.perf_counter()
import mujoco, mujoco_warp as mjw, warp as wp
wp.config.log_level = wp.LOG_WARNING
path, device, nworld, plugin = sys.argv[1], sys.argv[2], int(sys.argv[3]), sys.argv[4] == "1"
with wp.ScopedDevice(device):
  mjm = mujoco.MjModel.from_xml_path(path)
  m = mjw.put_model(mjm)
  t_install = time.perf_counter()
  if plugin:
    import mjx_supportfield
    from mjx_supportfield.launch import first_use
    mjx_supportfield.install(mjm, m)
  t_step = time.perf_counter()
  d = mjw.make_data(mjm, nworld=nworld)
  mjw.step(m, d)
  mjw.step(m, d)  # the first step's watch ends here
  wp.synchronize()
  t_end = time.perf_counter()
print(json.dumps({"import_and_load_s": t_install - t0, "install_s": t_step - t_install, "first_steps_s": t_end - t_step,
                  "stages": first_use.compile_history() if plugin else []}))
"""


def plugin_module_prefixes() -> tuple:
  """Names that begin the plugin's entries in Warp's kernel cache: its modules (``wp_mjx_supportfield.``)
  and the one-kernel modules its factories make (``wp_<factory>__locals__``)."""
  import ast

  names = set()
  for folder, _, files in os.walk(os.path.join(ROOT, "mjx_supportfield")):
    for f in files:
      if f.endswith(".py"):
        tree = ast.parse(open(os.path.join(folder, f)).read())
        names |= {n.name for n in ast.walk(tree) if isinstance(n, ast.FunctionDef)}
  return ("wp_mjx_supportfield",) + tuple(f"wp_{n}__locals__" for n in sorted(names))


def run_child(path: str, device: str, nworld: int, plugin: bool, env: dict) -> dict:
  out = subprocess.run([sys.executable, "-c", CHILD, path, device, str(nworld), "1" if plugin else "0"], env=env,
                       capture_output=True, text=True)
  if out.returncode:
    raise RuntimeError(f"{path}: {out.stderr[-2000:]}")
  return json.loads(out.stdout.strip().splitlines()[-1])


def main():
  p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
  p.add_argument("models", nargs="*")
  p.add_argument("--device", default="cpu")
  p.add_argument("--nworld", type=int, default=64)
  p.add_argument("--keep-mujoco-warp", action="store_true")
  p.add_argument("--base-cache", default=None, help="start from a copy of this kernel cache, less the plugin's modules")
  p.add_argument("--no-prebuilt", action="store_true", help="ignore the packs of prebuilt modules (MJX_SUPPORTFIELD_PREBUILT=off):"
                 " every module of the plugin compiles")
  p.add_argument("--json", default=None)
  args = p.parse_args()
  models = args.models or [os.path.join(HERE, "scenes", "pile_32_128.xml"), os.path.join(ROOT, "models", "terrain.xml"),
                           os.path.join(ROOT, "models", "real", "quadruped_rough.xml")]
  rows = []
  for path in models:
    cache = tempfile.mkdtemp(prefix="first_step_")
    try:
      env = {**os.environ, "WARP_CACHE_PATH": os.path.join(cache, "warp"),
             "MJX_SUPPORTFIELD_CACHE": os.path.join(cache, "install"), "PYTHONPATH": ROOT + os.pathsep
             + os.environ.get("PYTHONPATH", "")}
      if args.no_prebuilt:
        env["MJX_SUPPORTFIELD_PREBUILT"] = "off"
      if args.base_cache:
        shutil.copytree(args.base_cache, env["WARP_CACHE_PATH"])
        ours = plugin_module_prefixes()
        for folder, dirs, _ in os.walk(env["WARP_CACHE_PATH"]):
          for name in [x for x in dirs if x.startswith(ours)]:
            shutil.rmtree(os.path.join(folder, name))
            dirs.remove(name)
      if args.keep_mujoco_warp:
        run_child(path, args.device, args.nworld, False, env)
      r = run_child(path, args.device, args.nworld, True, env)
    finally:
      shutil.rmtree(cache, ignore_errors=True)
    by = {s["stage"]: s for s in r["stages"]}
    row = {"model": os.path.relpath(path, ROOT) if path.startswith(ROOT) else path, "device": args.device,
           "nworld": args.nworld, "mujoco_warp_cached": bool(args.keep_mujoco_warp or args.base_cache), **r,
           "plugin_first_collision_s": by.get("the plugin's first collision", {}).get("seconds", 0.0),
           "plugin_first_collision_modules": by.get("the plugin's first collision", {}).get("modules", 0),
           "plugin_modules_prebuilt": sum(s.get("prebuilt", 0) for s in r["stages"]), "prebuilt": not args.no_prebuilt,
           "install_kernels_s": sum(s["seconds"] for s in r["stages"] if s["stage"].startswith("install")),
           "mujoco_warp_first_step_s": by.get("MuJoCo Warp's first step", {}).get("seconds", 0.0)}
    rows.append(row)
    print(f"{row['model']}: install {row['install_s']:.1f} s (its kernels {row['install_kernels_s']:.1f} s), first "
          f"steps {row['first_steps_s']:.1f} s: MuJoCo Warp's modules {row['mujoco_warp_first_step_s']:.1f} s, the "
          f"plugin's first collision {row['plugin_first_collision_s']:.1f} s ({row['plugin_first_collision_modules']} "
          f"modules compiled, {row['plugin_modules_prebuilt']} of the plugin's loaded prebuilt)", flush=True)
  if args.json:
    with open(args.json, "w") as f:
      json.dump({"rows": rows, "cpu_count": os.cpu_count()}, f, indent=1)


if __name__ == "__main__":
  main()
