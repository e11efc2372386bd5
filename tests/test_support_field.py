"""Support field quality: exactness of the refined/exact modes on random hulls, the field-mode
error bound, poles and seam, tie counts, memory, and per-world mesh assignment."""

import functools

import numpy as np
import pytest
import warp as wp
from conftest import load

import mujoco
import mujoco_warp as mjw
import mjx_supportfield as sf
from mjx_supportfield.geometry import support
from mjx_supportfield.geometry import support_field
from mjx_supportfield.types import MeshSupport
from mjx_supportfield.types import SupportMode
from mjx_supportfield.types import mode_module

# the test kernels are only run forward: no adjoint code to build (on CUDA it would take minutes)
wp.set_module_options({"enable_backward": False})

RES = 180
NDIR = 100_000


def _points(rng, n, axes):
  p = rng.normal(size=(n, 3))
  return p / np.linalg.norm(p, axis=1, keepdims=True) * np.asarray(axes)


HULLS = {  # name: (points, scale)
  "tet8": lambda rng: _points(rng, 8, (1, 1, 1)),
  "ball64": lambda rng: _points(rng, 64, (1, 1, 1)),
  "flat512": lambda rng: _points(rng, 512, (1, 1, 0.01)),
  "needle512": lambda rng: _points(rng, 512, (0.01, 0.01, 1)),
  "ball4096": lambda rng: _points(rng, 4096, (1, 0.8, 0.6)),
  "cube": lambda rng: np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)], float),
}
SCALES = {"tet8": 1e-3, "ball64": 1.0, "flat512": 0.05, "needle512": 0.05, "ball4096": 1e2, "cube": 0.05}


@pytest.fixture(scope="module")
def hulls():
  rng = np.random.default_rng(7)
  assets, geoms = [], []
  for name, make in HULLS.items():
    pts = make(rng) * SCALES[name]
    assets.append(f'<mesh name="{name}" vertex="{" ".join(f"{x:.9g}" for x in pts.ravel())}"/>')
    geoms.append(f'<geom type="mesh" mesh="{name}"/>')
  # a second geom on the cube mesh: geoms sharing a mesh share its field
  geoms.append('<geom type="mesh" mesh="cube" pos="1 0 0"/>')
  xml = f"<mujoco><asset>{''.join(assets)}</asset><worldbody>{''.join(geoms)}</worldbody></mujoco>"
  mjm = mujoco.MjModel.from_xml_string(xml)
  m = mjw.put_model(mjm)
  ms = support_field.build_mesh_support(mjm, m.mesh_vert, RES)
  hd = support_field.hull_data(mjm)
  verts = []
  for i in range(mjm.nmesh):
    ids = hd.hull_vert[hd.hull_adr[i] : hd.hull_adr[i] + hd.hull_num[i]]
    verts.append(mjm.mesh_vert[mjm.mesh_vertadr[i] + ids].astype(np.float64))
  return mjm, ms, verts


@pytest.fixture(scope="module")
def directions():
  rng = np.random.default_rng(3)
  d = rng.normal(size=(NDIR, 3))
  d /= np.linalg.norm(d, axis=1, keepdims=True)
  special = [
    [0, 0, 1], [0, 0, -1],  # poles
    [1e-7, 0, 1], [0, -1e-7, -1], [0.01, 0.01, 1],  # next to the poles
    [-1, 0, 0], [-1, 1e-7, 0], [-1, -1e-7, 0], [-1, 0, 0.3], [-1, 1e-6, -0.3],  # the seam at theta = +-pi
    [1, 0, 0], [0, 1, 0], [0, -1, 0],
  ]
  special = np.array(special, float)
  special /= np.linalg.norm(special, axis=1, keepdims=True)
  return np.concatenate([special, d])


@functools.lru_cache(maxsize=None)
def _query(mode: int):
  """The support-point test kernel of one support mode (support.support_funcs), in a module of
  that mode: another mode's test adds a module instead of rebuilding this one."""
  mesh_support_index = support.support_funcs(mode).mesh_support_index

  @wp.kernel(module=mode_module(__name__, mode))
  def query(ms: MeshSupport, mesh: int, dirs: wp.array(dtype=wp.vec3), out: wp.array(dtype=wp.vec3)):
    i = wp.tid()
    out[i] = support.hull_point(ms, mesh, mesh_support_index(ms, mesh, dirs[i]))

  return query


@wp.kernel
def _ties(ms: MeshSupport, mesh: int, rtol: float, dirs: wp.array(dtype=wp.vec3), out: wp.array(dtype=int)):
  i = wp.tid()
  out[i] = support.count_supports(7, wp.vec3(0.0), mesh, ms, dirs[i], rtol)


@wp.kernel
def _box_ties(size: wp.vec3, rtol: float, dirs: wp.array(dtype=wp.vec3), out: wp.array(dtype=int)):
  i = wp.tid()
  out[i] = support.count_supports(6, size, -1, MeshSupport(), dirs[i], rtol)


def _run(ms, mesh, mode, dirs):
  out = wp.zeros(len(dirs), dtype=wp.vec3)
  wp.launch(_query(SupportMode.of(mode)), dim=len(dirs),
            inputs=[ms, mesh, wp.array(dirs.astype(np.float32), dtype=wp.vec3), out])
  return out.numpy().astype(np.float64)


@pytest.mark.parametrize("mode", ["refined", "exact"])
def test_exact_modes_match_exhaustive_scan(hulls, directions, mode):
  mjm, ms, verts = hulls
  for mesh, v in enumerate(verts):
    best = (directions @ v.T).max(axis=1)
    got = np.einsum("ij,ij->i", _run(ms, mesh, mode, directions), directions)
    scale = np.abs(v).max()
    # float32 storage: 1e-6 relative to the hull's extent
    assert np.all(got >= best - 1e-6 * scale), (list(HULLS)[mesh], mode, float((best - got).max() / scale))


def test_field_mode_within_bound(hulls, directions):
  mjm, ms, verts = hulls
  res = ms.field_res.numpy()
  for mesh, v in enumerate(verts):
    diameter = np.linalg.norm(v.max(axis=0) - v.min(axis=0))
    cell_angle = 2 * np.pi / res[mesh]
    best = (directions @ v.T).max(axis=1)
    got = np.einsum("ij,ij->i", _run(ms, mesh, "field", directions), directions)
    assert np.all(best - got <= diameter * cell_angle), list(HULLS)[mesh]


def _brute_ties(v, d, rtol):
  dots = v @ d
  best = int(np.argmax(dots))
  tol = rtol * max(np.linalg.norm(v[best] - v.mean(axis=0)), 1e-12)
  return int((dots >= dots[best] - tol).sum())


def test_tie_counts_match_brute_force(hulls, directions):
  mjm, ms, verts = hulls
  rtol = 1e-5
  for mesh, v in enumerate(verts):
    # face normals of the hull tie 3+ vertices; random directions tie none
    fadr, fnum = mjm.mesh_faceadr[mesh], mjm.mesh_facenum[mesh]
    faces = mjm.mesh_face[fadr : fadr + fnum]
    mv = mjm.mesh_vert[mjm.mesh_vertadr[mesh] :].astype(np.float64)
    normals = np.cross(mv[faces[:, 1]] - mv[faces[:, 0]], mv[faces[:, 2]] - mv[faces[:, 0]])
    normals = normals[np.linalg.norm(normals, axis=1) > 0]
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    dirs = np.concatenate([normals[:200], directions[:2000]])
    out = wp.zeros(len(dirs), dtype=int)
    wp.launch(_ties, dim=len(dirs), inputs=[ms, mesh, rtol, wp.array(dirs.astype(np.float32), dtype=wp.vec3), out])
    want = np.array([min(_brute_ties(v, d, rtol), support.TIE_STACK) for d in dirs])
    got = out.numpy()
    # float32 queries vs float64 reference: allow disagreement only on vertices within 10x tol
    loose = np.array([_brute_ties(v, d, 10 * rtol) for d in dirs])
    tight = np.array([_brute_ties(v, d, 0.1 * rtol) for d in dirs])
    assert np.all((got >= np.minimum(tight, support.TIE_STACK)) & (got <= np.minimum(loose, support.TIE_STACK))), list(HULLS)[mesh]
    assert np.mean(got == want) > 0.99
    assert got[: min(len(normals), 200)].min() >= 3 or list(HULLS)[mesh] in ("tet8",)


def test_box_ties():
  dirs = np.array([[0, 0, 1], [1, 0, 0], [1, 1, 0], [1, 1, 1], [0.3, -0.2, 0.9], [1e-9, 0, 1]], float)
  out = wp.zeros(len(dirs), dtype=int)
  wp.launch(_box_ties, dim=len(dirs), inputs=[wp.vec3(0.1, 0.2, 0.3), 1e-6, wp.array(dirs.astype(np.float32), dtype=wp.vec3), out])
  np.testing.assert_array_equal(out.numpy(), [4, 4, 2, 1, 1, 4])


def test_memory_and_sharing(hulls):
  mjm, ms, verts = hulls
  nbytes = support_field.field_bytes(ms)
  assert len(nbytes) == mjm.nmesh  # one field per mesh, not per geom (the cube mesh has two geoms)
  assert mjm.ngeom == mjm.nmesh + 1
  seed = 16 * RES * RES
  assert np.all(nbytes <= seed / 8), nbytes
  res = dict(zip(HULLS, ms.field_res.numpy()))
  assert res["cube"] <= 16  # coarse hulls get coarse fields
  # the dense round hull needs extras lists on many quads: a slightly coarser grid pays for them
  assert 0.8 * RES <= res["ball4096"] < RES


def test_support_res_caps_resolution():
  mjm = load("convex_pile").mjm
  m = mjw.put_model(mjm)
  ms = support_field.build_mesh_support(mjm, m.mesh_vert, 24)
  assert ms.field_res.numpy().max() <= 24
  fixed = support_field.build_mesh_support(mjm, m.mesh_vert, 24, adaptive=False)
  assert np.all(fixed.field_res.numpy() == 24)


PER_WORLD_XML = """
<mujoco>
  <asset>
    <mesh name="small" vertex="-.05 -.05 -.05 .05 -.05 -.05 -.05 .05 -.05 .05 .05 -.05 -.05 -.05 .05 .05 -.05 .05 -.05 .05 .05 .05 .05 .05"/>
    <mesh name="large" vertex="-.1 -.1 -.1 .1 -.1 -.1 -.1 .1 -.1 .1 .1 -.1 -.1 -.1 .1 .1 -.1 .1 -.1 .1 .1 .1 .1 .1"/>
  </asset>
  <worldbody>
    <geom name="base" type="box" size=".5 .5 .05"/>
    <body pos="0 0 0.099"><freejoint/><geom name="obj" type="mesh" mesh="small"/></body>
    <body pos="3 0 0.5"><freejoint/><geom name="other" type="mesh" mesh="large"/></body>
  </worldbody>
</mujoco>
"""


def test_per_world_mesh_assignment():
  """Domain randomization: world 1 swaps the object's mesh through a batched geom_dataid."""
  sim = load(PER_WORLD_XML, nworld=2)
  m, d, mjm = sim.m, sim.d, sim.mjm
  dataid = np.tile(mjm.geom_dataid, (2, 1)).astype(np.int32)
  obj = mujoco.mj_name2id(mjm, mujoco.mjtObj.mjOBJ_GEOM, "obj")
  dataid[1, obj] = mujoco.mj_name2id(mjm, mujoco.mjtObj.mjOBJ_MESH, "large")
  m.geom_dataid = wp.array(dataid, dtype=int)
  aabb = np.tile(mjm.geom_aabb.reshape(1, mjm.ngeom, 2, 3), (2, 1, 1, 1)).astype(np.float32)
  aabb[1, obj, 1] = 0.1
  m.geom_aabb = wp.array(aabb, dtype=wp.vec3)
  sf.install(mjm, m)
  sf.collision(m, d)
  n = int(d.nacon.numpy()[0])
  world, dist = d.contact.worldid.numpy()[:n], d.contact.dist.numpy()[:n]
  geom = d.contact.geom.numpy()[:n]
  depth = {w: -dist[(world == w) & (geom.max(axis=1) == obj)].min() for w in (0, 1)}
  assert depth[0] == pytest.approx(0.001, abs=1e-5)
  assert depth[1] == pytest.approx(0.051, abs=1e-4)


def test_proven_quads_are_exact(hulls, directions):
  """A query landing in a quad flagged at build time (CERTIFIED: one read; CORNERS_EXACT: best
  of the 4 corners) gets the exact support in ``field`` mode too, without a climb."""
  mjm, ms, verts = hulls
  _, proof_code = support_field.decode_field(ms)
  adr, res_all = ms.field_adr.numpy(), ms.field_res.numpy()
  certified_fraction, proven_fraction, listed_fraction = {}, {}, {}
  for mesh, v in enumerate(verts):
    res = int(res_all[mesh])
    theta = np.arctan2(directions[:, 1], directions[:, 0])
    phi = np.arccos(np.clip(directions[:, 2], -1, 1))
    i0 = np.floor((theta + np.pi) / (2 * np.pi) * res).astype(int) % res
    j0 = np.clip(np.floor(phi / np.pi * (res - 1)).astype(int), 0, res - 1)
    code = proof_code[adr[mesh] + j0 * res + i0]
    certified = code == support.CERTIFIED
    corners = certified | (code == support.CORNERS_EXACT)
    proven = corners | (code == support.WITH_EXTRAS)
    name = list(HULLS)[mesh]
    certified_fraction[name], proven_fraction[name] = certified.mean(), proven.mean()
    listed_fraction[name] = (code == support.WITH_EXTRAS).mean()
    best = (directions @ v.T).max(axis=1)
    scale = np.abs(v).max()
    # field mode weighs the 4 corners only; refined also the listed extras (and climbs nowhere else)
    for mode, exact in (("field", corners), ("refined", proven)):
      got = np.einsum("ij,ij->i", _run(ms, mesh, mode, directions), directions)
      assert np.all(got[exact] >= best[exact] - 1e-6 * scale), (name, mode)
  # most queries on medium hulls need one read; on the dense round hull the corners still
  # answer nearly all (the cube's coarse field needs no proof: its cell corners sit on the octant
  # boundaries, where vertices tie, and its plain lookup is exact)
  assert certified_fraction["ball64"] > 0.5 and certified_fraction["flat512"] > 0.3, certified_fraction
  assert proven_fraction["ball64"] > 0.99 and proven_fraction["flat512"] > 0.95, proven_fraction
  # ... and on the dense round hull, the extras lists cover the quads whose corners miss a vertex
  assert listed_fraction["ball4096"] > 0.05, listed_fraction
  assert proven_fraction["ball4096"] > 0.999, proven_fraction


def test_hull_graph_layout_checked_for_every_reader():
  """The hull graph has one parser: a graph whose neighbour lists do not end where MuJoCo's
  layout says makes every reader (neighbours, face planes, SDF triangles, the yardstick's
  faces) raise instead of reading faces from the wrong entries."""
  from mjx_supportfield.tools import exact
  from mjx_supportfield.geometry import sdf
  from mjx_supportfield.geometry.hull_graph import hull_graph

  cube = " ".join(f"{x} {y} {z}" for x in (-1, 1) for y in (-1, 1) for z in (-1, 1))
  mjm = mujoco.MjModel.from_xml_string(
    f'<mujoco><asset><mesh name="c" vertex="{cube}"/></asset><worldbody><geom type="mesh" mesh="c"/>'
    "</worldbody></mujoco>"
  )
  graph = hull_graph(mjm, 0)
  assert len(graph.vert) == 8 and graph.faces.shape == (12, 3) and graph.nbr_num.sum() == len(graph.nbr) == 36
  adr = mjm.mesh_graphadr[0]
  nvert = mjm.mesh_graph[adr]
  last_end = adr + 2 + 2 * nvert + len(graph.nbr) + nvert - 1  # the -1 that ends the last list
  mjm.mesh_graph[last_end] = 0
  readers = (support_field.mesh_hull, support_field.mesh_hull_planes, sdf.hull_triangles, exact.hull_faces)
  for reader in readers:
    with pytest.raises(ValueError, match="convex-hull graph"):
      reader(mjm, 0)
