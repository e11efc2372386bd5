"""The whole benchmark suite on the GPU: every scene, plugin vs stock MuJoCo Warp in one process.

  python benchmarks/run_suite.py [--only SCENE ...] [--launches N] [--out benchmarks/results]
                                 [--compile-jobs N] [--newton]

Writes <out>/<date>-<gpu>.json (the bench rows of every scene, install times and the
broad-phase scaling; rewritten after each scene, so a run cut short keeps what it measured)
and <out>/<date>-<gpu>.png. Missing generated scenes are written first (make_scenes.py).

Compiling MuJoCo Warp's step and the plugin for a new scene takes minutes on the first run;
``--compile-jobs N`` first runs every scene once, N scenes at a time in separate processes
(``--compile-only``), so the kernels compile in parallel into Warp's cache before the timed
runs, which then go one scene at a time.

``--newton`` adds Newton 1.8's collision pipeline on the same poses (the ``newton`` extra;
``mjx_supportfield/tools/newton_bench.py``): the JSON gains ``newton`` entries (best broad phase and its
ms inside the evolving poses, each broad phase's ms in steps and frozen, contacts per world).
"""

import argparse
import datetime
import json
import os
import subprocess
import sys
import time
from concurrent.futures import ThreadPoolExecutor

import mujoco
import mujoco_warp as mjw
import warp as wp

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.dirname(HERE))
sys.path.insert(0, HERE)

import make_scenes  # noqa: E402

from mjx_supportfield.driver import get_collider  # noqa: E402
from mjx_supportfield.driver import install  # noqa: E402
from mjx_supportfield.options import Options  # noqa: E402
from mjx_supportfield.stages import broadphase  # noqa: E402
from mjx_supportfield.tools import bench  # noqa: E402

MJW_DATA = os.path.join(os.path.dirname(mjw.__file__), "test_data")
SCENES = {  # name: (path, nworlds)
  "aloha_pot": (os.path.join(MJW_DATA, "aloha_pot", "scene.xml"), [1024, 4096, 8192]),
  "pile_32_128": (os.path.join(HERE, "scenes", "pile_32_128.xml"), [1024, 4096, 8192]),
  "pile_32_1024": (os.path.join(HERE, "scenes", "pile_32_1024.xml"), [1024, 8192]),
  # stock MuJoCo Warp's solver holds a dense nv x nv matrix a world (nv = 6 x meshes): the large
  # piles fit at these world counts (4096 worlds of 256 meshes, 256 of 1024 ran out of memory)
  "pile_256_128": (os.path.join(HERE, "scenes", "pile_256_128.xml"), [256, 1024]),
  "pile_1024_128": (os.path.join(HERE, "scenes", "pile_1024_128.xml"), [16]),
  "primitives_32": (os.path.join(HERE, "scenes", "primitives_32.xml"), [1024, 8192]),
  "primitives_layers_48": (os.path.join(HERE, "scenes", "primitives_layers_48.xml"), [1024, 4096, 8192]),
  "humanoid": (os.path.join(MJW_DATA, "humanoid", "humanoid.xml"), [1024, 8192]),
  "terrain_32": (os.path.join(HERE, "scenes", "terrain_32.xml"), [1024, 8192]),
}
# timed launches of scenes whose stock step is too slow for --launches (stock's dense solver on
# 1024 meshes: 300 launches of each implementation would take most of an hour of device time)
MAX_LAUNCHES = {"pile_1024_128": 10}
BROADPHASE_SCENES = ("pile_32_128", "pile_256_128", "pile_1024_128")
BROADPHASE_NWORLD = 256  # one world count for the broad-phase scaling, so only the geom count changes


def install_seconds(path: str) -> dict:
  """Seconds of ``install`` on a fresh model: first in this process, then again (kernels and SDFs cached)."""
  mjm = mujoco.MjModel.from_xml_path(path)
  out = {}
  for label in ("first", "again"):
    m = mjw.put_model(mjm)
    wp.synchronize()
    t = time.perf_counter()
    install(mjm, m, Options())
    wp.synchronize()
    out[label] = time.perf_counter() - t
  return out


def broadphase_ms(path: str, nworld: int, launches: int) -> list[dict]:
  """Graph-captured time of the plugin's broad phase alone (boxes, pairs, queues) at the settled
  state, with each ``Options.broadphase``: "sap" and "nxn"."""
  mjm = mujoco.MjModel.from_xml_path(path)
  mjd = bench.settled_state(mjm, 200)  # put_data copies its geom poses: no MuJoCo Warp kernel to compile
  rows = []
  for mode in ("sap", "nxn"):
    m = mjw.put_model(mjm)
    install(mjm, m, Options(broadphase=mode))
    d = mjw.put_data(mjm, mjd, nworld=nworld, nconmax=int(1.5 * mjd.ncon) + 16, njmax=6 * mjd.ncon + 64)
    collider = get_collider(m)
    st = collider.state(m, d)

    def run():
      for counter in (st.broad.world_npair, st.broad.npair, st.broad.nwarned, st.narrow.queue_count):  # the counters the broad phase adds to
        counter.zero_()
      broadphase.launch(collider, m, d, st.broad, st.narrow.queues, None)

    ms = bench._time_graph(run, launches)
    rows.append({"ngeom": mjm.ngeom, "nworld": nworld, "broadphase": mode, "ms": ms,
                 "pairs_per_world": int(st.broad.npair.numpy()[0]) / nworld})
  return rows


def broadphase_scaling(nworld: int, launches: int, out: str, suffix: str) -> None:
  """The broad phase alone on the 32-, 256- and 1024-mesh piles, sweep-and-prune and nxn:
  <out>/<date>-<device>-broadphase<suffix>.json."""
  scaling = []
  for name in BROADPHASE_SCENES:
    for row in broadphase_ms(SCENES[name][0], nworld, launches):
      scaling.append(row)
      print(json.dumps(row), flush=True)
  device = bench.device_name()
  tag = device.split()[-1].lower() if wp.get_device().is_cuda else "cpu"
  path = os.path.join(out, f"{datetime.date.today()}-{tag}-broadphase{suffix}.json")
  with open(path, "w") as f:
    json.dump({"device": device, "versions": {"warp": wp.__version__, "mujoco": mujoco.__version__},
               "launches": launches, "broadphase_scaling": scaling}, f, indent=1)
  print("wrote", path)


def compile_all(names: list[str], jobs: int, newton: bool = False) -> dict:
  """Runs each scene once (both implementations, and Newton's pipeline with ``newton``; at most 64
  worlds) in ``jobs`` parallel processes, so every kernel is in Warp's cache before timing. Returns
  each scene's exit status."""

  def one(name):
    cmd = [sys.executable, os.path.abspath(__file__), "--compile-only", "--only", name] + (["--newton"] if newton else [])
    t = time.perf_counter()
    rc = subprocess.run(cmd, stdout=subprocess.DEVNULL).returncode
    print(f"compiled {name}: exit {rc} after {time.perf_counter() - t:.0f} s", flush=True)
    return rc

  with ThreadPoolExecutor(jobs) as pool:
    return dict(zip(names, pool.map(one, names)))


def main(argv=None):
  p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
  p.add_argument("--only", nargs="*", choices=sorted(SCENES), help="scenes to run (default: all)")
  p.add_argument("--nworld", type=int, nargs="*", help="override every scene's nworld list")
  p.add_argument("--launches", type=int, default=100)
  p.add_argument("--out", default=os.path.join(HERE, "results"))
  p.add_argument("--suffix", default="", help="appended to the results' file names (runs split over calls)")
  p.add_argument("--options", default="{}", help="plugin Options as JSON, e.g. '{\"warm_start\": false}'")
  p.add_argument("--compile-jobs", type=int, default=0, help="compile the scenes in N parallel processes first")
  p.add_argument("--compile-only", action="store_true",
                 help="run each scene once at 64 worlds (fewer where the scene is timed at fewer), time nothing")
  p.add_argument("--broadphase-only", type=int, metavar="NWORLD",
                 help="time only the broad phase of the piles at NWORLD worlds, on the current device (CPU works)")
  p.add_argument("--newton", action="store_true",
                 help="also time Newton 1.8's collision pipeline on the same poses (pip install mjx-supportfield[newton])")
  args = p.parse_args(argv)
  newton_bench = None
  if args.newton:
    from mjx_supportfield.tools import newton_bench

    try:
      newton_bench.import_newton()
    except ImportError as e:
      p.error(str(e))
  wp.config.log_level = wp.LOG_WARNING
  names = args.only or list(SCENES)
  if any(not os.path.exists(SCENES[n][0]) for n in names):
    make_scenes.main()
  if args.compile_only:
    for name in names:  # at most the scene's smallest world count (the 1024-mesh pile's dense solver)
      bench.bench_scene(SCENES[name][0], [min(64, *SCENES[name][1])], 1, 200, None, Options())
      if newton_bench:
        newton_bench.bench_newton(SCENES[name][0], [min(64, *SCENES[name][1])], 1, 200)
    return
  if args.broadphase_only:
    broadphase_scaling(args.broadphase_only, args.launches, args.out, args.suffix)
    return
  if args.compile_jobs:
    compile_all(names, args.compile_jobs, args.newton)

  options = Options.from_dict(json.loads(args.options))
  plan = {n: (SCENES[n][0], args.nworld or SCENES[n][1]) for n in names}
  progress = bench.Progress(sum(2 * len(nw) for _, nw in plan.values()))
  rows, installs, scaling, newton_results = [], {}, [], []
  os.makedirs(args.out, exist_ok=True)
  gpu = bench.device_name()
  stem = os.path.join(args.out, f"{datetime.date.today()}-{gpu.split()[-1].lower()}{args.suffix}")
  launches = {}
  for name, (path, nworlds) in plan.items():
    launches[name] = min(args.launches, MAX_LAUNCHES.get(name, args.launches))
    installs[name] = install_seconds(path)
    rows += bench.bench_scene(path, nworlds, launches[name], 200, None, options, progress)
    if name in BROADPHASE_SCENES:
      scaling += broadphase_ms(path, BROADPHASE_NWORLD, args.launches)
    scene_rows = [r for r in rows if r.scene == bench.scene_name(path)]
    print(f"\n{bench.format_table(scene_rows)}", flush=True)
    extra = {"install_s": installs, "broadphase_scaling": scaling, "launches": launches,
             "options": json.loads(args.options)}
    if newton_bench:
      scene_newton = newton_bench.bench_newton(path, nworlds, launches[name], 200)
      newton_results += scene_newton
      print(newton_bench.format_newton(scene_newton, scene_rows), flush=True)
      extra.update(newton_bench.json_extra(newton_results))
    bench.write_json(rows, stem + ".json", extra=extra)

  try:
    bench.plot([r.__dict__ for r in rows], stem + ".png")
  except ImportError:
    print("matplotlib missing: no plot")
  print(bench.format_table(rows))
  if newton_bench:
    print(newton_bench.format_newton(newton_results, rows))
  print("install [s]:", json.dumps(installs))
  print("broad phase:", json.dumps(scaling))
  print("wrote", stem + ".json")


if __name__ == "__main__":
  main()
