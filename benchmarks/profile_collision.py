"""Per-kernel GPU time of one collision call, plugin and stock (Warp's CUDA activity timing).

  python benchmarks/profile_collision.py SCENE.xml [--nworld 8192] [--settle 200] [--variants V,V,...]

A variant is ``default`` or Options fields as ``key=value;key=value`` (Python literals), e.g.
``multi_contact=False;mpr_refine=0``.
"""

import ast

import argparse
import collections

import mujoco
import mujoco_warp as mjw
import warp as wp

from mjx_supportfield.bench import settled_state
from mjx_supportfield.install import install
from mjx_supportfield.options import Options


def main():
  p = argparse.ArgumentParser()
  p.add_argument("model")
  p.add_argument("--nworld", type=int, default=8192)
  p.add_argument("--settle", type=int, default=200)
  p.add_argument("--repeats", type=int, default=5)
  p.add_argument("--variants", default="default", help="plugin variants (see above), comma-separated")
  args = p.parse_args()
  wp.config.log_level = wp.LOG_WARNING
  mjm = mujoco.MjModel.from_xml_path(args.model)
  mjd = settled_state(mjm, args.settle)
  ncon = int(1.5 * mjd.ncon) + 16
  for impl in ["stock"] + args.variants.split(","):
    m = mjw.put_model(mjm)
    if impl != "stock":
      fields = dict(kv.split("=", 1) for kv in impl.split(";") if kv != "default")
      install(mjm, m, Options(**{k: ast.literal_eval(v) for k, v in fields.items()}))
    d = mjw.put_data(mjm, mjd, nworld=args.nworld, nconmax=ncon, njmax=6 * ncon + mjd.nefc)
    mjw.forward(m, d)
    mjw.collision(m, d)
    wp.synchronize()
    wp.timing_begin(cuda_filter=wp.TIMING_ALL)
    for _ in range(args.repeats):
      mjw.collision(m, d)
    wp.synchronize()
    results = wp.timing_end()
    per = collections.defaultdict(float)
    for r in results:
      per[r.name] += r.elapsed / args.repeats
    total = sum(per.values())
    print(f"== {impl}: {total:.3f} ms of GPU activity per collision, nworld {args.nworld}")
    for name, ms in sorted(per.items(), key=lambda x: -x[1])[:12]:
      print(f"  {ms:8.3f} ms  {name[:90]}")


if __name__ == "__main__":
  main()
