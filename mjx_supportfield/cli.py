"""Command line: ``mjx-supportfield compare MODEL.xml`` (and ``python -m mjx_supportfield``)."""

import argparse
import math
import os
import sys


def _compare(args) -> int:
  import warp as wp

  wp.config.log_level = wp.LOG_WARNING  # no per-module compile lines
  from mjx_supportfield.compare import check
  from mjx_supportfield.compare import compare
  from mjx_supportfield.compare import format_report
  from mjx_supportfield.compare import write_json
  from mjx_supportfield.options import Options

  import json

  extra = json.loads(args.options)
  options = Options.from_dict({"support_mode": args.support_mode, "support_res": args.support_res,
                               "narrowphase": args.narrowphase, **extra})
  with wp.ScopedDevice(args.device):
    report = compare(args.model, steps=args.steps, samples=args.samples, nworld=args.nworld, min_depth=args.min_depth,
                     options=options, radius=args.radius)
  print(format_report(report))
  if args.json:
    write_json(report, args.json)
    print(f"wrote {args.json}")
  reasons = check(report)
  if args.check and reasons:
    print("check failed: " + "; ".join(reasons), file=sys.stderr)
    return 1
  return 0


def _bench(args) -> int:
  import json

  import warp as wp

  wp.config.log_level = wp.LOG_WARNING
  from mjx_supportfield import bench
  from mjx_supportfield.options import Options

  nworlds = [int(x) for x in args.nworld.split(",")]
  rows = []
  with wp.ScopedDevice(args.device):
    progress = bench.Progress(len(args.model) * len(nworlds) * 2)
    for path in args.model:
      rows += bench.bench_scene(path, nworlds, args.steps, args.settle, args.nconmax, Options(), progress)
      if args.json:  # after each scene, so a run cut short keeps what it measured
        bench.write_json(rows, args.json)
    print(f"device: {bench.device_name()}")
    print(bench.format_table(rows))
    if args.json:
      print(f"wrote {args.json}")
  if args.plot:
    try:
      bench.plot([r.__dict__ for r in rows], args.plot)
      print(f"wrote {args.plot}")
    except ImportError:
      print("--plot needs matplotlib (pip install matplotlib); use 'mjx-supportfield plot RESULTS.json OUT.png' "
            "where it is installed", file=sys.stderr)
  return 0


def _plot(args) -> int:
  import json

  from mjx_supportfield import bench

  with open(args.results) as f:
    bench.plot(json.load(f)["rows"], args.out)
  print(f"wrote {args.out}")
  return 0


def _parser() -> argparse.ArgumentParser:
  p = argparse.ArgumentParser(prog="mjx-supportfield", description="Support-field collision plugin for MuJoCo Warp")
  sub = p.add_subparsers(dest="command", required=True)
  c = sub.add_parser("compare", help="compare contacts with MuJoCo C and stock MuJoCo Warp",
                     description="Contacts of the plugin and stock MuJoCo Warp against MuJoCo C's on states of a "
                                 "MuJoCo C rollout, judged with exact float64 geometry on MuJoCo C's poses.")
  c.add_argument("model", help="MJCF file")
  c.add_argument("--steps", type=int, default=200, help="MuJoCo C steps to roll out (default 200)")
  c.add_argument("--samples", type=int, default=5, help="states sampled along the rollout (default 5)")
  c.add_argument("--nworld", type=int, default=None, help="worlds (default: one per sampled state)")
  c.add_argument("--min-depth", type=float, default=5e-4,
                 help="depth [m] from which MuJoCo C's contact points and pairs count as deep (5e-4)")
  c.add_argument("--radius", type=float, default=3e-3,
                 help="a deep point is found when a contact of its pair lies within this distance [m] (3e-3)")
  c.add_argument("--support-mode", default="refined", help="field | refined | exact")
  c.add_argument("--support-res", type=int, default=180)
  c.add_argument("--narrowphase", default="mpr", help="mpr | gjk (the plugin's convex penetration solver)")
  c.add_argument("--options", default="{}", help="further plugin Options as JSON, e.g. '{\"warm_start\": false}'")
  c.add_argument("--device", default=None, help="Warp device, e.g. cpu or cuda:0 (default: Warp's default)")
  c.add_argument("--json", default=None, help="write the full report here")
  c.add_argument("--check", action="store_true",
                 help="exit 1 if the plugin misses more than 2%% of MuJoCo C's deep points (no contact of the pair "
                      "within --radius), has a normal more than 5 deg from MuJoCo C's that is worse by exact overlap "
                      "of the two convex shapes, or has a contact more than |dist|/2 + 1 mm outside either geom")
  c.set_defaults(func=_compare)

  b = sub.add_parser("bench", help="time the plugin against stock MuJoCo Warp (collision stage and step)")
  b.add_argument("model", nargs="+", help="MJCF file(s)")
  b.add_argument("--nworld", default="1024,4096,8192", help="comma-separated world counts")
  b.add_argument("--steps", type=int, default=100, help="timed graph launches per measurement (>= 100)")
  b.add_argument("--settle", type=int, default=200, help="MuJoCo C steps before timing, to start in contact")
  b.add_argument("--nconmax", type=int, default=None, help="contacts per world to allocate (MuJoCo Warp default)")
  b.add_argument("--device", default=None)
  b.add_argument("--json", default=None, help="write rows as JSON")
  b.add_argument("--plot", default=None, help="write a PNG of time vs nworld (needs matplotlib)")
  b.set_defaults(func=_bench)

  pl = sub.add_parser("plot", help="plot a bench JSON file")
  pl.add_argument("results")
  pl.add_argument("out")
  pl.set_defaults(func=_plot)
  return p


def main(argv=None) -> int:
  """Entry point of the ``mjx-supportfield`` console script."""
  args = _parser().parse_args(argv)
  models = args.model if isinstance(getattr(args, "model", None), list) else [getattr(args, "model", None)]
  for path in models:
    if path is None:
      continue
    if not os.path.isfile(path):
      return _error(f"model file not found: {path}")
    try:  # validate before Warp starts (and prints its own banner)
      import mujoco

      mujoco.MjModel.from_xml_path(path)
    except ValueError as e:
      return _error(f"{path}: {e}")
  if args.command == "compare":
    for name, low in (("steps", 0), ("samples", 1), ("nworld", 1)):
      value = getattr(args, name)
      if value is not None and value < low:
        return _error(f"--{name} must be >= {low}, got {value}")
    for name, positive in (("min_depth", False), ("radius", True)):
      value = getattr(args, name)
      if not math.isfinite(value) or value < 0 or (positive and value == 0):
        return _error(f"--{name.replace('_', '-')} must be a finite {'positive' if positive else 'non-negative'} "
                      f"length in metres, got {value}")
  try:
    return args.func(args)
  except ValueError as e:  # invalid options, bad model, mismatched models
    return _error(str(e))


def _error(message: str) -> int:
  """Prints one error line (multi-line messages, such as MuJoCo's XML errors, are joined)."""
  line = "; ".join(x.strip() for x in message.splitlines() if x.strip())
  print(f"mjx-supportfield: error: {line}", file=sys.stderr)
  return 2


if __name__ == "__main__":
  sys.exit(main())
