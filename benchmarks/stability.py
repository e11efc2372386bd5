"""Resting-contact stability of the plugin, stock MuJoCo Warp and MuJoCo C on the same scenes.

  python benchmarks/stability.py [--steps 2000] [--settle 200] [--engines plugin,mjw,mujoco]
                                 [--scenes resting,box_stack] [--json OUT]

Every engine steps the scene from its initial state (nworld=1 for MuJoCo Warp) and records, at
each step, the free bodies' positions and orientations (qpos) and the contacts (geom pair,
position). The figures (drift, contact motion, whether the stack stands; defined in
``scenelib.stability``) are over the window after settling (steps ``settle`` to ``steps``).

tests/test_stability.py measures with the same ``simulate`` and ``measure``, so the test and
this table measure the same thing.
"""

import argparse
import json
import platform
import time

import mujoco

from scenelib.stability import ENGINES
from scenelib.stability import MAX_CONTACT_MOTION
from scenelib.stability import MAX_DRIFT
from scenelib.stability import SCENES
from scenelib.stability import STAND_TILT
from scenelib.stability import STAND_XY
from scenelib.stability import STAND_Z
from scenelib.stability import measure
from scenelib.stability import model_path
from scenelib.stability import simulate


def run(scenes, engines, nstep: int, settle: int, log=print) -> dict:
  """{scene: {engine: measure(...)}} for every scene and engine."""
  results = {}
  for scene in scenes:
    mjm = mujoco.MjModel.from_xml_path(model_path(scene))
    names = [mujoco.mj_id2name(mjm, mujoco.mjtObj.mjOBJ_GEOM, i) for i in range(mjm.ngeom)]
    for engine in engines:
      t0 = time.perf_counter()
      traj = simulate(scene, engine, nstep, mjm=mjm)
      res = measure(traj, settle, names)
      res["wall_seconds"] = time.perf_counter() - t0
      results.setdefault(scene, {})[engine] = res
      log(f"# {scene} / {engine}: {res['ms_per_step']:.2f} ms/step after the first, which took"
          f" {traj.first_seconds:.1f} s; {res['wall_seconds']:.1f} s in all")
  return results


def table(results: dict) -> str:
  """Markdown tables of run()'s results: bodies, geom pairs and the stack, per scene."""
  lines = []
  for scene, by_engine in results.items():
    engines = list(by_engine)
    lines += _body_rows(scene, by_engine, engines) + _pair_rows(scene, by_engine, engines)
    if "stack" in by_engine[engines[0]]:
      lines += _stack_rows(by_engine, engines)
    lines.append(f"\n* over the threshold (drift {MAX_DRIFT:g} m, contact motion {MAX_CONTACT_MOTION:g} m)")
    lines.append("ms per step (after the first): " + ", ".join(f"{e} {by_engine[e]['ms_per_step']:.2f}" for e in engines))
  return "\n".join(lines)


def _row(label, cells) -> str:
  return f"| {label} | " + " | ".join(cells) + " |"


def _body_rows(scene, by_engine, engines) -> list:
  lines = [f"\n{scene}: drift [m] after settling, final z [m], final tilt [deg] ({' / '.join(engines)})",
           _row("body", [f"{k} {e}" for k in ("drift", "z", "tilt") for e in engines]),
           "|---" * (1 + 3 * len(engines)) + "|"]
  for body in by_engine[engines[0]]["bodies"]:
    b = [by_engine[e]["bodies"][body] for e in engines]
    lines.append(_row(body, [_flag(x["drift"], MAX_DRIFT) for x in b] + [f"{x['final_z']:.5f}" for x in b]
                      + [f"{x['final_tilt_deg']:.3f}" for x in b]))
  return lines


def _pair_rows(scene, by_engine, engines) -> list:
  lines = [f"\n{scene}: max contact-point motion per step [m] (count changes, appearances)",
           _row("pair", engines), "|---" * (1 + len(engines)) + "|"]
  for pair in sorted({p for e in engines for p in by_engine[e]["pairs"]}):
    recs = [by_engine[e]["pairs"].get(pair) for e in engines]
    lines.append(_row(pair, ["-" if r is None else
                             f"{_flag(r['max_motion'], MAX_CONTACT_MOTION)} ({r['count_changes']}, {r['appearances']})"
                             for r in recs]))
  return lines


def _stack_rows(by_engine, engines) -> list:
  st = [by_engine[e]["stack"] for e in engines]
  return ["", _row("stack", engines), "|---" * (1 + len(engines)) + "|",
          _row("standing", ["yes" if s["standing"] else "NO" for s in st]),
          _row("max xy move [m]", [f"{s['max_xy']:.2e}" for s in st]),
          _row("max z move [m]", [f"{s['max_dz']:.2e}" for s in st]),
          _row("max tilt [deg]", [f"{s['max_tilt_deg']:.3f}" for s in st])]


def _flag(value: float, limit: float) -> str:
  return f"{value:.2e}" + ("*" if not value < limit else "")


def _csv(value: str, allowed) -> list:
  items = [x for x in value.split(",") if x]
  bad = [x for x in items if x not in allowed]
  if bad or not items:
    raise argparse.ArgumentTypeError(f"expected a comma-separated subset of {', '.join(allowed)}, got {value!r}")
  return items


def main(argv=None):
  p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
  p.add_argument("--steps", type=int, default=2000)
  p.add_argument("--settle", type=int, default=200, help="steps before drift and contact motion are measured")
  p.add_argument("--engines", type=lambda v: _csv(v, ENGINES), default=list(ENGINES))
  p.add_argument("--scenes", type=lambda v: _csv(v, SCENES), default=list(SCENES))
  p.add_argument("--json", metavar="OUT", help="write the results as JSON")
  args = p.parse_args(argv)
  if not 0 <= args.settle < args.steps:
    p.error(f"--settle must be in [0, --steps), got {args.settle}")
  if any(e != "mujoco" for e in args.engines):
    import warp as wp

    wp.config.quiet = True
    wp.config.log_level = wp.LOG_WARNING
  results = run(args.scenes, args.engines, args.steps, args.settle)
  print(table(results))
  if args.json:
    import mujoco_warp
    import warp as wp

    meta = {"steps": args.steps, "settle": args.settle, "mujoco": mujoco.__version__,
            "warp": wp.config.version, "mujoco_warp": getattr(mujoco_warp, "__version__", "?"),
            "device": str(wp.get_device()), "machine": platform.platform(),
            "thresholds": {"drift": MAX_DRIFT, "contact_motion": MAX_CONTACT_MOTION,
                           "stand_xy": STAND_XY, "stand_z": STAND_Z, "stand_tilt_deg": STAND_TILT}}
    with open(args.json, "w") as f:
      json.dump({"meta": meta, "results": results}, f, indent=1)


if __name__ == "__main__":
  main()
