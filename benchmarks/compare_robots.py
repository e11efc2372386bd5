"""``compare`` on robots as shipped: aloha_pot, every gripper and hand of robosuite 1.5.2, and
robosuite's arms with their hands (benchmarks/robosuite_arms.py), plugin and stock MuJoCo Warp
against MuJoCo C.

  python benchmarks/compare_robots.py [--json OUT] [--only NAME ...]

robosuite's files come from its wheel, fetched once into the cache (robosuite_arms.fetch). Files
MuJoCo cannot load as shipped (robosuite's own errors) and models whose states hold no contact are
listed, not compared. Prints one row a scene: MuJoCo C's deep points, those the plugin and stock
miss, the plugin's normals worse than C's, points off their shapes, and compare's --check
verdict; writes the rows, with each report's per-point lists, as JSON.
"""

import argparse
import glob
import json
import os
import sys

import mujoco

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, HERE)
sys.path.insert(0, os.path.dirname(HERE))  # this checkout's package, as the other benchmarks
import robosuite_arms  # noqa: E402

from mjx_supportfield.tools import compare  # noqa: E402


def scenes() -> dict:
  """{name: MJCF path}: aloha_pot, robosuite's grippers and hands, its arms with their hands."""
  import mujoco_warp
  out = {"aloha_pot": os.path.join(os.path.dirname(mujoco_warp.__file__), "test_data", "aloha_pot", "scene.xml")}
  assets = robosuite_arms.fetch(robosuite_arms.cache_dir())
  for path in sorted(glob.glob(os.path.join(assets, "grippers", "*.xml"))):
    out[f"gripper:{os.path.splitext(os.path.basename(path))[0]}"] = path
  for arm, path in robosuite_arms.write_scenes().items():
    out[f"arm:{arm}"] = path
  return out


def row(name: str, path: str) -> dict:
  """compare's figures for one scene, or why it was not compared."""
  try:
    mujoco.MjModel.from_xml_path(path)
  except ValueError as e:
    return {"scene": name, "skipped": f"MuJoCo cannot load it as shipped: {str(e).splitlines()[0]}"}
  try:
    report = compare.compare(path)
  except ValueError as e:
    return {"scene": name, "skipped": str(e).split(": ", 1)[-1]}
  plugin, stock = (report["impls"][k]["summary"] for k in ("plugin", "stock"))
  if plugin["contacts_reference"] == 0:
    return {"scene": name, "skipped": "no contacts in the sampled states"}
  return {"scene": name, "deep_points": plugin["deep_points_reference"], "plugin_missed": plugin["deep_points_missed"],
          "stock_missed": stock["deep_points_missed"],
          "missed_where_mujoco_is_worse": plugin["deep_points_missed_reference_worse"],
          "normals_worse": plugin["pairs_normal_worse"],
          "off_shapes": plugin["contacts_outside"], "contacts": plugin["contacts"],
          "contacts_mujoco": plugin["contacts_reference"], "contacts_stock": stock["contacts"],
          "check": compare.check(report), "missed_list": plugin["deep_points_missed_list"]}


def main(argv=None) -> int:
  parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
  parser.add_argument("--json", default=None)
  parser.add_argument("--only", nargs="*", default=None, help="scene names (default: all)")
  args = parser.parse_args(argv)
  rows = []
  for name, path in scenes().items():
    if args.only and name not in args.only:
      continue
    r = row(name, path)
    rows.append(r)
    if "skipped" in r:
      print(f"{name}: not compared: {r['skipped']}", flush=True)
      continue
    verdict = "passes" if not r["check"] else "fails: " + "; ".join(r["check"])
    print(f"{name}: {r['plugin_missed']} of {r['deep_points']} deep points missed (stock {r['stock_missed']}; "
          f"{r['missed_where_mujoco_is_worse']} on pairs where MuJoCo C's normal is the worse one), "
          f"{r['normals_worse']} worse normals, {r['off_shapes']} off shapes, contacts {r['contacts']} "
          f"(C {r['contacts_mujoco']}, stock {r['contacts_stock']}): {verdict}", flush=True)
  compared = [r for r in rows if "skipped" not in r]
  total = sum(r["deep_points"] for r in compared)
  print(f"all: {sum(r['plugin_missed'] for r in compared)} of {total} deep points missed "
        f"(stock {sum(r['stock_missed'] for r in compared)})")
  if args.json:
    with open(args.json, "w") as f:
      json.dump(rows, f, indent=1)
  return 0


if __name__ == "__main__":
  sys.exit(main())
