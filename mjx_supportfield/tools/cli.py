"""Command line: ``mjx-supportfield compare MODEL.xml`` (and ``python -m mjx_supportfield``).

Warp, MuJoCo Warp and the plugin's modules are imported inside the commands: importing them takes
seconds, which ``--help``, ``--version`` and argument errors should not wait for.
"""

import argparse
import contextlib
import json
import logging
import math
import os
import sys

_PROG = "mjx-supportfield"


def _version() -> str:
  """The installed distribution's version (package metadata), else the source tree's."""
  import importlib.metadata

  try:
    return importlib.metadata.version("mjx_supportfield")
  except importlib.metadata.PackageNotFoundError:
    from mjx_supportfield import __version__

    return __version__


# --- argument types: a bad value is an argparse error naming the argument -------------------------


def _json_object(text: str) -> dict:
  """--options: a JSON object of plugin Options fields."""
  try:
    value = json.loads(text)
  except json.JSONDecodeError:
    value = None
  if not isinstance(value, dict):
    raise argparse.ArgumentTypeError(
      f"expected a JSON object of Options fields, such as '{{\"warm_start\": false, \"mpr_refine\": 1}}', "
      f"got {text!r}")
  return value


def _world_counts(text: str) -> list:
  """--nworld of bench: comma-separated positive integers."""
  try:
    counts = [int(x) for x in text.split(",")]
  except ValueError:
    counts = []
  if not counts or min(counts) < 1:
    raise argparse.ArgumentTypeError(f"expected positive world counts separated by commas, such as 1024,4096; "
                                     f"got {text!r}")
  return counts


# --- commands -------------------------------------------------------------------------------


def _quiet_warp():
  """Imports Warp with its banner and per-module load lines off: the plugin announces the
  compilation of kernels that are not cached yet (mjx_supportfield.launch.first_use) instead."""
  import warp as wp

  wp.config.log_level = wp.LOG_WARNING
  return wp


def _compare(args) -> int:
  wp = _quiet_warp()
  from mjx_supportfield.launch import first_use
  from mjx_supportfield.tools.compare import check
  from mjx_supportfield.tools.compare import compare
  from mjx_supportfield.tools.compare import format_report
  from mjx_supportfield.tools.compare import write_json
  from mjx_supportfield.options import Options

  options = Options.from_dict({"support_mode": args.support_mode, "support_res": args.support_res,
                               "narrowphase": args.narrowphase, **args.options})
  with wp.ScopedDevice(args.device), first_use.announce_compiles("compare"):
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
  wp = _quiet_warp()
  from mjx_supportfield.tools import bench
  from mjx_supportfield.options import Options

  if args.steps < bench.MIN_LAUNCHES:
    return _error(f"--steps must be >= {bench.MIN_LAUNCHES}, got {args.steps}: each time is the mean of this many "
                  "launches, and fewer leave it to launch overhead and the clock's resolution")
  with wp.ScopedDevice(args.device):
    nworlds = args.nworld
    if nworlds is None:
      nworlds = list(bench.default_world_counts())
      where = "a GPU" if wp.get_device().is_cuda else "the CPU"
      print(f"nworld {','.join(map(str, nworlds))}: the default on {where} (GPU: "
            f"{','.join(map(str, bench.GPU_WORLDS))}, CPU: {','.join(map(str, bench.CPU_WORLDS))}); "
            "--nworld picks others", flush=True)
    newton_bench = None
    if args.newton:
      from mjx_supportfield.tools import newton_bench
      try:
        newton_bench.import_newton()
      except ImportError as e:
        return _error(str(e))
    print(f"device: {bench.device_description()}", flush=True)
    rows, newton_results = [], []
    progress = bench.Progress(len(args.model) * len(nworlds) * 2)
    for path in args.model:
      rows += bench.bench_scene(path, nworlds, args.steps, args.settle, args.nconmax, Options(), progress,
                                args.keyframe)
      if newton_bench:
        newton_results += newton_bench.bench_newton(path, nworlds, args.steps, args.settle, args.nconmax,
                                                    keyframe=args.keyframe)
      if args.json:  # after each scene, so a run cut short keeps what it measured
        bench.write_json(rows, args.json, extra=newton_bench.json_extra(newton_results) if newton_bench else None)
    print(bench.format_table(rows))
    if newton_bench:
      print(newton_bench.format_newton(newton_results, rows))
    if args.json:
      print(f"wrote {args.json}")
    device = bench.device_description()
  if args.plot:
    try:
      bench.plot([r.__dict__ for r in rows], args.plot, device)
      print(f"wrote {args.plot}")
    except ImportError:
      print("--plot needs matplotlib (pip install matplotlib); use 'mjx-supportfield plot RESULTS.json OUT.png' "
            "where it is installed", file=sys.stderr)
  return 0


def _plot(args) -> int:
  from mjx_supportfield.tools import bench

  data = bench.load_results(args.results)
  try:
    import matplotlib  # noqa: F401
  except ImportError:
    return _error("plot needs matplotlib: pip install matplotlib (or pip install 'mjx_supportfield[plot]')")
  try:
    bench.plot(data["rows"], args.out, data.get("device") or data.get("gpu"))
  except OSError as e:
    return _error(f"cannot write {args.out}: {e.strerror or e}")
  print(f"wrote {args.out}")
  return 0


class _Parser(argparse.ArgumentParser):
  """argparse, with a usage error in one line (the usage is a --help away)."""

  def error(self, message):
    self.exit(2, f"{self.prog}: error: {message} (see {self.prog} --help)\n")


class _Version(argparse.Action):
  """--version: read from the package metadata only when asked (it scans the installed packages)."""

  def __init__(self, option_strings, dest=argparse.SUPPRESS, default=argparse.SUPPRESS, help=None):
    super().__init__(option_strings, dest=dest, default=default, nargs=0, help=help)

  def __call__(self, parser, namespace, values, option_string=None):
    print(f"{_PROG} {_version()}")
    parser.exit()


def _parser() -> argparse.ArgumentParser:
  p = _Parser(prog=_PROG, description="Support-field collision plugin for MuJoCo Warp")
  p.add_argument("--version", action=_Version, help="print the installed version and exit")
  sub = p.add_subparsers(dest="command", required=True, metavar="{compare,bench,plot}")
  c = sub.add_parser("compare", help="compare contacts with MuJoCo C and stock MuJoCo Warp",
                     description="Contacts of the plugin and stock MuJoCo Warp against MuJoCo C's on states of a "
                                 "MuJoCo C rollout, judged with exact float64 geometry on MuJoCo C's poses. "
                                 "The first run compiles Warp kernels (about a minute on a CPU, several on a GPU); "
                                 "later runs load them from Warp's kernel cache.")
  c.add_argument("model", help="MJCF file, or a compiled model (.mjb, mujoco.mj_saveModel's)")
  c.add_argument("--steps", type=int, default=200, help="MuJoCo C steps to roll out (default 200)")
  c.add_argument("--samples", type=int, default=5, help="states sampled along the rollout (default 5)")
  c.add_argument("--nworld", type=int, default=None, help="worlds (default: one per sampled state)")
  c.add_argument("--min-depth", type=float, default=5e-4,
                 help="depth [m] from which MuJoCo C's contact points and pairs count as deep (5e-4)")
  c.add_argument("--radius", type=float, default=3e-3,
                 help="a deep point is found when a contact of its pair lies within this distance [m] (3e-3)")
  c.add_argument("--support-mode", default="refined",
                 help="how convex-mesh support points are found: field (lookup in the precomputed direction "
                      "table, approximate), refined (table, then a walk on the hull: exact; default) or exact "
                      "(scan of every hull vertex)")
  c.add_argument("--support-res", type=int, default=180,
                 help="directions per axis of each mesh's support table (4 to 4096; default 180)")
  c.add_argument("--narrowphase", default="mpr", help="mpr | gjk (the plugin's convex penetration solver)")
  c.add_argument("--options", type=_json_object, default={},
                 help="further plugin Options as a JSON object, e.g. '{\"warm_start\": false}' "
                      "(fields: python -c 'import mjx_supportfield; help(mjx_supportfield.Options)')")
  c.add_argument("--device", default=None, help="Warp device, e.g. cpu or cuda:0 (default: Warp's default)")
  c.add_argument("--json", default=None, help="write the full report here")
  c.add_argument("--check", action="store_true",
                 help="exit 1 if the plugin misses more than 2%% of MuJoCo C's deep points (no contact of the pair "
                      "within --radius), has a normal more than 5 deg from MuJoCo C's that is worse by exact overlap "
                      "of the two convex shapes, or has a contact more than |dist|/2 + 1 mm outside either geom")
  c.set_defaults(func=_compare)

  b = sub.add_parser("bench", help="time the plugin against stock MuJoCo Warp (collision stage and step)",
                     description="Times the plugin and stock MuJoCo Warp on each model: the collision stage and "
                                 "the whole step, graph-captured on a GPU.")
  b.add_argument("model", nargs="+", help="MJCF file(s), or compiled models (.mjb)")
  b.add_argument("--nworld", type=_world_counts, default=None,
                 help="comma-separated world counts (default: 1024,4096,8192 on a GPU, 1,8,64 on the CPU, where a "
                      "step costs about nworld times one world's)")
  b.add_argument("--steps", type=int, default=100, help="timed launches per measurement (default and minimum 100)")
  b.add_argument("--settle", type=int, default=200, help="MuJoCo C steps before timing, to start in contact")
  b.add_argument("--keyframe", type=int, default=None,
                 help="settle from this keyframe of each model instead of qpos0 (robots that stand where a "
                 "keyframe puts them)")
  b.add_argument("--nconmax", type=int, default=None, help="contacts per world to allocate for both implementations (default: from MuJoCo C's settled contacts, doubled while either overflows)")
  b.add_argument("--device", default=None, help="Warp device, e.g. cpu or cuda:0 (default: Warp's default)")
  b.add_argument("--json", default=None, help="write rows as JSON")
  b.add_argument("--plot", default=None, help="write a PNG of time vs nworld (needs matplotlib)")
  b.add_argument("--newton", action="store_true",
                 help="also time Newton 1.8's collision pipeline on the same poses, each broad phase "
                      "(needs the newton extra: pip install mjx-supportfield[newton])")
  b.set_defaults(func=_bench)

  pl = sub.add_parser("plot", help="plot a bench JSON file", description="Draws what 'bench --json' wrote.")
  pl.add_argument("results", help="JSON file written by 'mjx-supportfield bench --json'")
  pl.add_argument("out", help="PNG to write")
  pl.set_defaults(func=_plot)
  return p


def _check_model(path: str, keyframe=None, newton: bool = False):
  """None if ``path`` is an MJCF file MuJoCo compiles or a compiled model (``.mjb``; not for
  Newton, which reads MJCF), with keyframe ``keyframe`` if given, else the error line."""
  if os.path.isdir(path):
    xml = sorted(f for f in os.listdir(path) if f.endswith(".xml"))
    hint = f" (it holds {', '.join(xml[:3])}{', ...' if len(xml) > 3 else ''})" if xml else ""
    return f"{path} is a directory; give an MJCF model file{hint}"
  if not os.path.isfile(path):
    return f"model file not found: {path}"
  if newton and path.endswith(".mjb"):
    return f"{path}: --newton reads MJCF (Newton's importer), not a compiled model"
  from mjx_supportfield.tools.model_file import load_model

  try:  # before Warp starts and compiles kernels
    mjm = load_model(path)
  except ValueError as e:
    return f"{path}: {e}"
  if keyframe is not None and keyframe >= mjm.nkey:
    return f"--keyframe {keyframe}: {path} has {mjm.nkey} keyframe(s)"
  return None


def _check_args(args):
  """None if the numeric arguments are in range, else the error line."""
  if args.command == "compare":
    for name, low in (("steps", 0), ("samples", 1), ("nworld", 1)):
      value = getattr(args, name)
      if value is not None and value < low:
        return f"--{name} must be >= {low}, got {value}"
    for name, positive in (("min_depth", False), ("radius", True)):
      value = getattr(args, name)
      if not math.isfinite(value) or value < 0 or (positive and value == 0):
        return (f"--{name.replace('_', '-')} must be a finite {'positive' if positive else 'non-negative'} "
                f"length in metres, got {value}")
  if args.command == "bench":
    if args.settle < 0:
      return f"--settle must be >= 0, got {args.settle}"
    if args.nconmax is not None and args.nconmax < 1:
      return f"--nconmax must be >= 1, got {args.nconmax}"
    if args.keyframe is not None and args.keyframe < 0:
      return f"--keyframe must be >= 0, got {args.keyframe}"
  return None


def _check_device(name):
  """None if Warp has the device ``name`` (None: its default), else the error line."""
  if name is None:
    return None
  wp = _quiet_warp()
  try:
    wp.get_device(name)
  except Exception:  # Warp raises RuntimeError or ValueError depending on the name
    have = ", ".join(d.alias for d in wp.get_devices())
    return f"--device {name}: Warp has no such device here (it has {have})"
  return None


def main(argv=None) -> int:
  """Entry point of the ``mjx-supportfield`` console script."""
  args = _parser().parse_args(argv)
  models = args.model if isinstance(getattr(args, "model", None), list) else [getattr(args, "model", None)]
  for path in models:
    if path is not None and (problem := _check_model(path, getattr(args, "keyframe", None),
                                                     getattr(args, "newton", False))):
      return _error(problem)
  problem = _check_args(args) or _check_device(getattr(args, "device", None))
  if problem:
    return _error(problem)
  with _compile_log():
    try:
      return args.func(args)
    except ValueError as e:  # invalid options, bad model, mismatched models, a file that is not bench results
      return _error(str(e))


@contextlib.contextmanager
def _compile_log():
  """Shows the plugin's notes on kernel compilation (logger mjx_supportfield, INFO) on stderr."""
  logger = logging.getLogger("mjx_supportfield")
  handler = logging.StreamHandler(sys.stderr)
  handler.setLevel(logging.INFO)
  handler.setFormatter(logging.Formatter("%(message)s"))
  logger.addHandler(handler)
  try:
    yield
  finally:
    logger.removeHandler(handler)


def _error(message: str) -> int:
  """Prints one error line (multi-line messages, such as MuJoCo's XML errors, are joined)."""
  line = "; ".join(x.strip() for x in message.splitlines() if x.strip())
  print(f"{_PROG}: error: {line}", file=sys.stderr)
  return 2


if __name__ == "__main__":
  sys.exit(main())
