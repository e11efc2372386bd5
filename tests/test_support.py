"""Support functions: closed forms of the primitives, the support field of convex meshes."""

import functools

import mujoco
import mujoco_warp as mjw
import numpy as np
import pytest
import warp as wp
from mujoco_warp._src.types import GeomType

from mjx_supportfield.geometry import support
from mjx_supportfield.geometry import support_field
from mjx_supportfield.types import MeshSupport
from mjx_supportfield.types import SupportMode
from mjx_supportfield.types import mode_module
from conftest import load_mjmodel

# the test kernels are only run forward: no adjoint code to build (on CUDA it would take minutes)
wp.set_module_options({"enable_backward": False})

NRANDOM = 3000


@functools.lru_cache(maxsize=None)
def _support_kernels(mode: int):
  """The test kernels on the support functions of one support mode (support.support_funcs), in a
  module of that mode: another mode's test adds a module instead of rebuilding this one."""
  funcs = support.support_funcs(mode)
  module = mode_module(__name__, mode)

  @wp.kernel(module=module)
  def support_local_kernel(
    gtype: int,
    size: wp.vec3,
    mesh: int,
    ms: MeshSupport,
    dirs: wp.array(dtype=wp.vec3),
    out: wp.array(dtype=wp.vec3),
  ):
    i = wp.tid()
    out[i] = funcs.support_local(gtype, size, mesh, ms, dirs[i])

  @wp.kernel(module=module)
  def mesh_index_kernel(
    ms: MeshSupport,
    mesh: int,
    dirs: wp.array(dtype=wp.vec3),
    idx_out: wp.array(dtype=int),
    point_out: wp.array(dtype=wp.vec3),
  ):
    i = wp.tid()
    k = funcs.mesh_support_index(ms, mesh, dirs[i])
    idx_out[i] = k
    point_out[i] = support.hull_point(ms, mesh, k)

  return support_local_kernel, mesh_index_kernel


def directions(rng, n=NRANDOM):
  """Random unit directions plus the axes, the poles, the seam (y = +-0, x < 0) and near-pole ones."""
  d = rng.normal(size=(n, 3))
  d /= np.linalg.norm(d, axis=1, keepdims=True)
  special = [
    [1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1],
    [1e-7, 0, 1], [-1e-7, 1e-7, 1], [1e-7, -1e-7, -1], [0, 1e-6, -1],
  ]
  for z in np.linspace(-0.99, 0.99, 23):
    x = -np.sqrt(1 - z * z)
    special.append([x, 0.0, z])
    special.append([x, -0.0, z])
    special.append([x, 1e-7, z])
    special.append([x, -1e-7, z])
  special = np.array(special, dtype=np.float64)
  special[:, 1] = np.copysign(np.abs(special[:, 1]), special[:, 1])  # keep the sign of zero
  special /= np.linalg.norm(special, axis=1, keepdims=True)
  return np.concatenate([special, d]).astype(np.float32)


def _seam_dirs_have_signed_zero():
  d = directions(np.random.default_rng(0))
  return np.any(np.signbit(d[:, 1]) & (d[:, 1] == 0) & (d[:, 0] < 0))


def test_directions_include_seam_and_poles():
  d = directions(np.random.default_rng(0))
  assert _seam_dirs_have_signed_zero()
  assert np.any((d[:, 1] == 0) & ~np.signbit(d[:, 1]) & (d[:, 0] < 0))
  assert np.any(np.all(d == [0, 0, 1], axis=1)) and np.any(np.all(d == [0, 0, -1], axis=1))


# --- a mesh model shared by all tests -----------------------------------------------------


@pytest.fixture(scope="module")
def pile():
  mjm = load_mjmodel("convex_pile")
  m = mjw.put_model(mjm)
  return mjm, m


@pytest.fixture(scope="module")
def mesh_supports(pile):
  mjm, m = pile
  return {res: support_field.build_mesh_support(mjm, m.mesh_vert, res) for res in (8, 45, 180)}


def run_support_local(ms, gtype, size, dirs, mesh=-1, mode="refined"):
  out = wp.zeros(len(dirs), dtype=wp.vec3)
  wp.launch(
    _support_kernels(SupportMode.of(mode))[0],
    dim=len(dirs),
    inputs=[int(gtype), wp.vec3(*size), mesh, ms, wp.array(dirs, dtype=wp.vec3)],
    outputs=[out],
  )
  return out.numpy().astype(np.float64)


# --- primitives ---------------------------------------------------------------------------


def surface_samples(gtype, size, n=40000, seed=3):
  """Dense sample of a primitive's surface (edges and cap rims included)."""
  rng = np.random.default_rng(seed)
  size = np.asarray(size, dtype=np.float64)
  u = rng.normal(size=(n, 3))
  u /= np.linalg.norm(u, axis=1, keepdims=True)
  if gtype == GeomType.SPHERE:
    return size[0] * u
  if gtype == GeomType.ELLIPSOID:
    return u * size
  if gtype == GeomType.CAPSULE:
    r, h = size[0], size[1]
    caps = r * u + np.where(u[:, 2:3] >= 0, 1.0, -1.0) * np.array([0, 0, h])
    t = rng.uniform(0, 2 * np.pi, n)
    side = np.stack([r * np.cos(t), r * np.sin(t), rng.uniform(-h, h, n)], axis=1)
    return np.concatenate([caps, side])
  if gtype == GeomType.CYLINDER:
    r, h = size[0], size[1]
    t = rng.uniform(0, 2 * np.pi, n)
    rim = np.stack([r * np.cos(t), r * np.sin(t), np.where(rng.random(n) < 0.5, h, -h)], axis=1)
    side = np.stack([r * np.cos(t), r * np.sin(t), rng.uniform(-h, h, n)], axis=1)
    rr = r * np.sqrt(rng.random(n))
    cap = np.stack([rr * np.cos(t), rr * np.sin(t), np.where(rng.random(n) < 0.5, h, -h)], axis=1)
    return np.concatenate([rim, side, cap])
  if gtype == GeomType.BOX:
    corners = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)]) * size
    p = rng.uniform(-1, 1, (n, 3)) * size
    axis = rng.integers(0, 3, n)
    p[np.arange(n), axis] = np.where(rng.random(n) < 0.5, -1.0, 1.0) * size[axis]
    return np.concatenate([corners, p])
  raise ValueError(gtype)


def support_value(gtype, size, d):
  """Closed-form support function h(d) = max_x x.d for unit rows d."""
  s = np.asarray(size, dtype=np.float64)
  if gtype == GeomType.SPHERE:
    return s[0] * np.ones(len(d))
  if gtype == GeomType.ELLIPSOID:
    return np.sqrt(np.sum((d * s) ** 2, axis=1))
  if gtype == GeomType.CAPSULE:
    return s[0] + s[1] * np.abs(d[:, 2])
  if gtype == GeomType.CYLINDER:
    return s[0] * np.hypot(d[:, 0], d[:, 1]) + s[1] * np.abs(d[:, 2])
  if gtype == GeomType.BOX:
    return np.abs(d) @ s
  raise ValueError(gtype)


def on_surface_error(gtype, size, p):
  """Distance-like measure of how far points p are from the primitive's surface."""
  s = np.asarray(size, dtype=np.float64)
  if gtype == GeomType.SPHERE:
    return np.abs(np.linalg.norm(p, axis=1) - s[0])
  if gtype == GeomType.ELLIPSOID:
    return np.abs(np.sqrt(np.sum((p / s) ** 2, axis=1)) - 1.0) * s.min()
  if gtype == GeomType.CAPSULE:
    z = np.clip(p[:, 2], -s[1], s[1])
    return np.abs(np.linalg.norm(p - np.stack([0 * z, 0 * z, z], axis=1), axis=1) - s[0])
  if gtype == GeomType.CYLINDER:
    rxy = np.hypot(p[:, 0], p[:, 1])
    inside = np.maximum(rxy - s[0], np.abs(p[:, 2]) - s[1])  # signed distance-ish (<= 0 inside)
    return np.abs(inside)
  if gtype == GeomType.BOX:
    return np.abs(np.max(np.abs(p) - s, axis=1))
  raise ValueError(gtype)


PRIMITIVES = [
  (GeomType.SPHERE, (0.07, 0.0, 0.0)),
  (GeomType.ELLIPSOID, (0.06, 0.025, 0.04)),
  (GeomType.ELLIPSOID, (0.01, 0.1, 0.003)),
  (GeomType.CAPSULE, (0.03, 0.08, 0.0)),
  (GeomType.CYLINDER, (0.04, 0.05, 0.0)),
  (GeomType.CYLINDER, (0.1, 0.005, 0.0)),
  (GeomType.BOX, (0.05, 0.02, 0.11)),
]


@pytest.mark.parametrize("gtype,size", PRIMITIVES, ids=lambda x: getattr(x, "name", None) or str(x))
def test_primitive_support(mesh_supports, gtype, size):
  ms = mesh_supports[8]
  rng = np.random.default_rng(int(gtype) * 7 + int(1000 * size[0]))
  dirs = directions(rng)
  d64 = dirs.astype(np.float64)
  p = run_support_local(ms, gtype, size, dirs)
  scale = max(size)
  assert np.all(np.isfinite(p))

  # the point lies on the surface
  err = on_surface_error(gtype, size, p)
  assert err.max() <= 2e-6 * scale, f"support point off the surface by {err.max():.3g}"
  # it attains the closed-form support value ...
  h = support_value(gtype, size, d64)
  dots = np.sum(p * d64, axis=1)
  assert np.max(np.abs(dots - h)) <= 2e-6 * scale
  # ... and no sampled surface point goes further
  samples = surface_samples(gtype, size)
  best = np.max(d64 @ samples.T, axis=1)
  assert np.all(dots >= best - 2e-6 * scale), f"worst shortfall {np.max(best - dots):.3g}"


@pytest.mark.parametrize("gtype,size", PRIMITIVES[:2] + PRIMITIVES[3:5] + PRIMITIVES[6:], ids=lambda x: getattr(x, "name", None) or str(x))
def test_primitive_support_scale_invariant(mesh_supports, gtype, size):
  """d need not be unit: scaling it does not move the support point."""
  ms = mesh_supports[8]
  dirs = directions(np.random.default_rng(11), 500)
  p1 = run_support_local(ms, gtype, size, dirs)
  for s in (1e-3, 37.0):
    p2 = run_support_local(ms, gtype, size, (dirs * s).astype(np.float32))
    np.testing.assert_allclose(p2, p1, atol=1e-6 * max(size))


# --- convex meshes ------------------------------------------------------------------------


def mesh_vertices(mjm, meshid):
  adr, n = mjm.mesh_vertadr[meshid], mjm.mesh_vertnum[meshid]
  return mjm.mesh_vert[adr : adr + n].astype(np.float64)


def run_mesh_index(ms, mesh, mode, dirs):
  n = len(dirs)
  idx = wp.zeros(n, dtype=int)
  pts = wp.zeros(n, dtype=wp.vec3)
  wp.launch(_support_kernels(SupportMode.of(mode))[1], dim=n, inputs=[ms, mesh, wp.array(dirs, dtype=wp.vec3)],
            outputs=[idx, pts])
  return idx.numpy(), pts.numpy().astype(np.float64)


def test_hull_data_matches_meshes(pile):
  """MuJoCo's hulls of the generated meshes keep every vertex; neighbour lists are symmetric."""
  mjm, _ = pile
  hd = support_field.hull_data(mjm)
  assert mjm.nmesh == 6
  for meshid in range(mjm.nmesh):
    n = int(hd.hull_num[meshid])
    assert n == mjm.mesh_vertnum[meshid]
    adr = int(hd.hull_adr[meshid])
    verts = hd.hull_vert[adr : adr + n]
    assert sorted(verts.tolist()) == list(range(n))
    nbrs = []
    for k in range(n):
      a, c = hd.nbr_adr[adr + k], hd.nbr_num[adr + k]
      nbrs.append(set(hd.nbr[a : a + c].tolist()))
      assert c >= 3 and all(0 <= x < n and x != k for x in nbrs[-1])
    for k in range(n):
      for x in nbrs[k]:
        assert k in nbrs[x], f"mesh {meshid}: edge {k}-{x} is one-sided"
    center = hd.hull_center[meshid]
    np.testing.assert_allclose(center, mesh_vertices(mjm, meshid).mean(axis=0), atol=1e-6)


@pytest.mark.parametrize("res", [8, 45, 180])
@pytest.mark.parametrize("mode", ["exact", "refined"])
def test_mesh_support_exact_modes(pile, mesh_supports, mode, res):
  mjm, _ = pile
  ms = mesh_supports[res]
  rng = np.random.default_rng(res)
  dirs = directions(rng)
  d64 = dirs.astype(np.float64)
  for meshid in range(mjm.nmesh):
    verts = mesh_vertices(mjm, meshid)
    idx, pts = run_mesh_index(ms, meshid, mode, dirs)
    assert np.all((idx >= 0) & (idx < mjm.mesh_vertnum[meshid]))
    # the returned point is a vertex of the mesh
    dist = np.min(np.linalg.norm(pts[:, None, :] - verts[None], axis=2), axis=1)
    assert dist.max() < 1e-7
    true = np.max(d64 @ verts.T, axis=1)
    got = np.sum(pts * d64, axis=1)
    tol = 1e-6 * np.max(np.linalg.norm(verts, axis=1))
    bad = np.nonzero(np.abs(got - true) > tol)[0]
    assert bad.size == 0, (
      f"mesh {meshid}, {mode}, res {res}: {bad.size} directions miss the support, e.g. d={dirs[bad[0]]}"
      f" got {got[bad[0]]:.7f} want {true[bad[0]]:.7f}"
    )
    # support_local agrees with mesh_support_index
    p = run_support_local(ms, GeomType.MESH, (0, 0, 0), dirs, mesh=meshid, mode=mode)
    np.testing.assert_array_equal(p, pts)


@pytest.mark.parametrize("res", [8, 45, 180])
def test_mesh_support_field_bound(pile, mesh_supports, res):
  """"field" mode is within diameter x cell angle (2 pi / res, res as asked for) of the exact
  support. (The builder may give a mesh a coarser field than asked for when that one is exact
  on its check set, never a finer one.)"""
  mjm, _ = pile
  ms = mesh_supports[res]
  field_res = ms.field_res.numpy()
  assert np.all((field_res >= 4) & (field_res <= res)), f"field resolutions {field_res} for res {res}"
  rng = np.random.default_rng(100 + res)
  dirs = directions(rng)
  d64 = dirs.astype(np.float64)
  for meshid in range(mjm.nmesh):
    verts = mesh_vertices(mjm, meshid)
    diameter = np.max(np.linalg.norm(verts[:, None] - verts[None], axis=2))
    idx, pts = run_mesh_index(ms, meshid, "field", dirs)
    assert np.all((idx >= 0) & (idx < mjm.mesh_vertnum[meshid]))
    dist = np.min(np.linalg.norm(pts[:, None, :] - verts[None], axis=2), axis=1)
    assert dist.max() < 1e-7
    true = np.max(d64 @ verts.T, axis=1)
    got = np.sum(pts * d64, axis=1)
    assert np.all(got <= true + 1e-7)
    short = true - got
    bound = diameter * 2 * np.pi / res
    bad = np.nonzero(short > bound)[0]
    assert bad.size == 0, (
      f"mesh {meshid}, res {res} (field {field_res[meshid]}): field support short by {short[bad].max():.3g} > {bound:.3g}"
      f" (diameter x cell angle), e.g. d={dirs[bad[0]]}"
    )


def test_field_cells_hold_cell_support(pile, mesh_supports):
  """Every field cell holds the support vertex of its own direction (theta = 2 pi i / res - pi,
  phi = pi j / (res - 1))."""
  mjm, _ = pile
  for res in (8, 45):
    ms = mesh_supports[res]
    field, _ = support_field.decode_field(ms)  # the top bits carry proofs
    adr = ms.field_adr.numpy()
    field_res = ms.field_res.numpy()
    hull_adr = ms.hull_adr.numpy()
    hull_vert = ms.hull_vert.numpy()
    for meshid in range(mjm.nmesh):
      r = int(field_res[meshid])
      i, j = np.meshgrid(np.arange(r), np.arange(r), indexing="xy")
      theta = 2 * np.pi * i / r - np.pi
      phi = np.pi * j / (r - 1)
      cell_dir = np.stack([np.sin(phi) * np.cos(theta), np.sin(phi) * np.sin(theta), np.cos(phi)], -1).reshape(-1, 3)
      verts = mesh_vertices(mjm, meshid)
      cells = field[adr[meshid] : adr[meshid] + r * r]
      assert np.all((cells >= 0) & (cells < mjm.mesh_vertnum[meshid]))
      local = hull_vert[hull_adr[meshid] + cells]
      got = np.sum(verts[local] * cell_dir, axis=1)
      true = np.max(cell_dir @ verts.T, axis=1)
      np.testing.assert_allclose(got, true, atol=1e-7, err_msg=f"mesh {meshid}, res {r}")


def test_hull_planes_support_the_hull(pile):
  """The hull face planes (for spheres sunk in meshes): unit outward normals, every vertex
  behind every plane, each plane touching the hull, points inside the hull behind all of them."""
  mjm, _ = pile
  hd = support_field.hull_data(mjm)
  rng = np.random.default_rng(0)
  for meshid in range(mjm.nmesh):
    planes = hd.plane[hd.plane_adr[meshid] : hd.plane_adr[meshid] + hd.plane_num[meshid]].astype(np.float64)
    assert len(planes) >= 4
    n, offset = planes[:, :3], planes[:, 3]
    np.testing.assert_allclose(np.linalg.norm(n, axis=1), 1.0, atol=1e-6)
    v = mesh_vertices(mjm, meshid)
    size = np.ptp(v, axis=0).max()
    heights = v @ n.T - offset  # <= 0: behind
    assert heights.max() <= 1e-6 * size
    assert np.all(heights.max(axis=0) >= -1e-6 * size)
    center = v.mean(axis=0)
    inside = center + 0.5 * (v[rng.integers(len(v), size=50)] - center)
    assert np.all((inside @ n.T - offset).max(axis=1) < 0)


def test_hull_planes_of_a_cube():
  """A cube mesh: its 12 hull triangles give the 6 face planes, each twice."""
  xml = """<mujoco><asset><mesh name="c" vertex="-1 -1 -1  1 -1 -1  -1 1 -1  1 1 -1  -1 -1 1  1 -1 1  -1 1 1  1 1 1"/>
    </asset><worldbody><geom type="mesh" mesh="c"/></worldbody></mujoco>"""
  mjm = mujoco.MjModel.from_xml_string(xml)
  planes = support_field.mesh_hull_planes(mjm, 0)
  assert len(planes) == 12
  faces = {tuple(np.round(p, 5)) for p in planes}
  expected = {tuple(float(x) for x in np.round(np.r_[s * np.eye(3)[k], 1.0], 5)) for k in range(3) for s in (-1, 1)}
  assert faces == expected
