"""Support-field benchmark: query throughput, exactness, memory and build time.

  python benchmarks/support_query.py [--queries N] [--json OUT]

Query throughput of the four ways to answer a convex-mesh support query, for hulls of 16 to
4096 vertices, with random and with temporally coherent directions:
  field    the seed's 4-cell lookup (approximate)
  refined  field vertex, then hill-climb on the hull graph (exact; the default)
  exact    exhaustive scan of the hull vertices
  climb    MuJoCo Warp's way: hill-climb from the previous query's vertex
Times are also given net of a run that only generates the directions ("net"): the cost
of the query itself. Also: fraction of queries that are exact, bytes per mesh vs the seed's 16 B x res^2, and
build time for 1, 100 and 1000 meshes of 64, 512 and 4096 hull vertices.
"""

import argparse
import json
import platform
import time

import mujoco
import numpy as np
import warp as wp

from mjx_supportfield.geometry import support as sp
from mjx_supportfield.geometry import support_field as sf
from mjx_supportfield.types import MeshSupport

QUERIES_PER_THREAD = 16
SEED_BYTES_PER_CELL = 16


def sphere_hull(n: int, seed: int = 0) -> mujoco.MjModel:
  """A model with one mesh: n random points on a sphere of radius 5 cm (all on the hull)."""
  rng = np.random.default_rng(seed)
  p = rng.normal(size=(n, 3))
  p = 0.05 * p / np.linalg.norm(p, axis=1, keepdims=True)
  xml = f'<mujoco><asset><mesh name="m" vertex="{" ".join(f"{x:.7f}" for x in p.ravel())}"/></asset>' \
        '<worldbody><geom type="mesh" mesh="m"/></worldbody></mujoco>'
  return mujoco.MjModel.from_xml_string(xml)


def replicated_support(mjm: mujoco.MjModel, copies: int, res: int, device, adaptive: bool = True):
  """MeshSupport of ``copies`` separate copies of the model's one mesh (nothing shared)."""
  hd = sf.hull_data(mjm)
  nv = mjm.mesh_vertnum[0]
  nh = int(hd.hull_num[0])
  rep = sf.HullData(
    hull_adr=(np.arange(copies) * nh).astype(np.int32),
    hull_num=np.full(copies, nh, np.int32),
    hull_vert=np.tile(hd.hull_vert, copies),
    hull_center=np.tile(hd.hull_center, (copies, 1)),
    nbr_adr=(np.tile(hd.nbr_adr, copies) + np.repeat(np.arange(copies) * len(hd.nbr), nh)).astype(np.int32),
    nbr_num=np.tile(hd.nbr_num, copies),
    nbr=np.tile(hd.nbr, copies),
  )
  vert = wp.array(np.tile(mjm.mesh_vert[:nv], (copies, 1)), dtype=wp.vec3, device=device)
  vertadr = (np.arange(copies) * nv).astype(np.int32)
  return sf.build_from_hulls(rep, vert, vertadr, res, device, adaptive)


@wp.func
def _direction(seed: int, i: int, k: int, coherent: int) -> wp.vec3:
  state = wp.rand_init(seed, i * 977 + wp.where(coherent == 1, 0, k))
  d = wp.sample_unit_sphere_surface(state)
  if coherent == 1:
    # a slow rotation: successive queries of a thread differ by ~0.01 rad
    axis = wp.normalize(wp.cross(d, wp.vec3(0.3, 0.5, 0.8)))
    d = wp.quat_rotate(wp.quat_from_axis_angle(axis, 0.01 * float(k)), d)
  return d


# the support query of each mode (support_funcs builds them per mode); the kernels below pick one
# at run time, as the plugin's kernels did before the mode was fixed at code generation
_FIELD = sp.support_funcs(0)
_REFINED = sp.support_funcs(1)
_EXACT = sp.support_funcs(2)


@wp.func
def _mesh_support_index(ms: MeshSupport, mesh: int, d: wp.vec3, mode: int) -> int:
  if mode == 0:
    return _FIELD.mesh_support_index(ms, mesh, d)
  if mode == 1:
    return _REFINED.mesh_support_index(ms, mesh, d)
  return _EXACT.mesh_support_index(ms, mesh, d)


@wp.kernel
def query_kernel(ms: MeshSupport, nmesh: int, mode: int, coherent: int, seed: int, out: wp.array(dtype=float)):
  """mode 0 field, 1 refined, 2 exact, 3 hill-climb from the previous vertex, -1 no query."""
  i = wp.tid()
  mesh = i % nmesh
  acc = float(0.0)
  prev = int(0)
  for k in range(QUERIES_PER_THREAD):
    d = _direction(seed, i, k, coherent)
    if mode == -1:
      acc += d[0]  # the loop and the direction alone: subtracted from the others
      continue
    if mode == 3:
      prev = sp.hill_climb(ms, mesh, prev, d)
      v = prev
    else:
      v = _mesh_support_index(ms, mesh, d, mode)
    acc += wp.dot(sp.hull_point(ms, mesh, v), d)
  out[i] = acc


@wp.kernel
def exactness_kernel(ms: MeshSupport, nmesh: int, mode: int, coherent: int, seed: int, out: wp.array(dtype=int)):
  """1 per query whose dot product equals the exhaustive maximum (1e-6 relative)."""
  i = wp.tid()
  mesh = i % nmesh
  prev = int(0)
  n = int(0)
  for k in range(QUERIES_PER_THREAD):
    d = _direction(seed, i, k, coherent)
    if mode == 3:
      prev = sp.hill_climb(ms, mesh, prev, d)
      v = prev
    else:
      v = _mesh_support_index(ms, mesh, d, mode)
    got = wp.dot(sp.hull_point(ms, mesh, v), d)
    best = wp.dot(sp.hull_point(ms, mesh, sp.hull_scan(ms, mesh, d)), d)
    if got >= best - 1.0e-6 * wp.abs(best):
      n += 1
  out[i] = n


def time_queries(ms, nmesh, mode, coherent, nthread, device, repeats=5) -> float:
  """Seconds per launch of nthread x QUERIES_PER_THREAD queries (best of ``repeats``)."""
  out = wp.zeros(nthread, dtype=float, device=device)
  wp.launch(query_kernel, dim=nthread, inputs=[ms, nmesh, mode, coherent, 0, out], device=device)
  wp.synchronize_device(device)
  best = float("inf")
  for r in range(repeats):
    t = time.perf_counter()
    wp.launch(query_kernel, dim=nthread, inputs=[ms, nmesh, mode, coherent, r + 1, out], device=device)
    wp.synchronize_device(device)
    best = min(best, time.perf_counter() - t)
  return best


def exact_fraction(ms, nmesh, mode, coherent, nthread, device) -> float:
  out = wp.zeros(nthread, dtype=int, device=device)
  wp.launch(exactness_kernel, dim=nthread, inputs=[ms, nmesh, mode, coherent, 123, out], device=device)
  return float(out.numpy().sum()) / (nthread * QUERIES_PER_THREAD)


MODES = {"field": 0, "refined": 1, "exact": 2, "climb": 3}


def main():
  p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
  p.add_argument("--threads", type=int, default=1 << 18, help="threads per launch (x16 queries each)")
  p.add_argument("--sizes", default="16,64,256,1024,4096", help="hull sizes for the query benchmark")
  p.add_argument("--build-sizes", default="64,512,4096")
  p.add_argument("--build-counts", default="1,100,1000")
  p.add_argument("--res", type=int, default=180)
  p.add_argument("--meshes", type=int, default=8, help="distinct meshes per query benchmark")
  p.add_argument("--device", default=None)
  p.add_argument("--json", default=None)
  args = p.parse_args()
  wp.config.log_level = wp.LOG_WARNING
  device = wp.get_device(args.device)
  rows, builds = [], []
  for n in [int(x) for x in args.sizes.split(",")]:
    mjm = sphere_hull(n)
    ms = replicated_support(mjm, args.meshes, args.res, device)
    res = int(ms.field_res.numpy()[0])
    for coherent in (0, 1):
      overhead = time_queries(ms, args.meshes, -1, coherent, args.threads, device)
      for name, mode in MODES.items():
        secs = time_queries(ms, args.meshes, mode, coherent, args.threads, device)
        nq = args.threads * QUERIES_PER_THREAD
        net = max(secs - overhead, 1e-12)
        row = {"hull_vertices": int(ms.hull_num.numpy()[0]), "directions": "coherent" if coherent else "random",
               "mode": name, "mqueries_per_s": nq / secs / 1e6, "ns_per_query": secs / nq * 1e9,
               "net_ns_per_query": net / nq * 1e9, "overhead_ns_per_query": overhead / nq * 1e9,
               "exact_fraction": exact_fraction(ms, args.meshes, mode, coherent, min(args.threads, 1 << 16), device),
               "field_res": res, "field_bytes": int(sf.field_bytes(ms)[0]),
               "seed_bytes": SEED_BYTES_PER_CELL * args.res * args.res}
        rows.append(row)
        print(f"hull {row['hull_vertices']:5d} {row['directions']:8s} {name:8s} {row['mqueries_per_s']:10.1f} Mq/s "
              f"{row['ns_per_query']:8.3f} ns/q (net of direction generation {row['net_ns_per_query']:8.3f}) exact {row['exact_fraction']:.6f}  res {res} "
              f"{row['field_bytes']} B/mesh (seed {row['seed_bytes']} B)", flush=True)
  for n in [int(x) for x in args.build_sizes.split(",")]:
    mjm = sphere_hull(n, seed=1)
    for count in [int(x) for x in args.build_counts.split(",")]:
      replicated_support(mjm, 1, args.res, device)  # warm the kernels
      wp.synchronize_device(device)
      t = time.perf_counter()
      ms = replicated_support(mjm, count, args.res, device)
      wp.synchronize_device(device)
      secs = time.perf_counter() - t
      b = {"hull_vertices": int(ms.hull_num.numpy()[0]), "meshes": count, "build_s": secs,
           "field_bytes_total": int(sf.field_bytes(ms).sum())}
      builds.append(b)
      print(f"build {count:5d} meshes x {b['hull_vertices']:5d} hull vertices: {secs:.3f} s, "
            f"{b['field_bytes_total'] / 1e6:.2f} MB of fields", flush=True)
  if args.json:
    gpu = device.name if device.is_cuda else platform.processor() or "cpu"
    with open(args.json, "w") as f:
      json.dump({"gpu": gpu, "device": str(device), "versions": {"warp": wp.__version__, "mujoco": mujoco.__version__},
                 "threads": args.threads, "queries_per_thread": QUERIES_PER_THREAD, "queries": rows, "builds": builds},
                f, indent=1)
    print(f"wrote {args.json}")


if __name__ == "__main__":
  main()
