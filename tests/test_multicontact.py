"""Multi-contact: face clipping where the normal lies along a flat face, pose perturbation
(the tilts) for the rest. Flat patches get points spread over the patch, at the right depth;
spheres and ellipsoids keep one point; the option turns it off."""

import numpy as np
import pytest
import warp as wp
from conftest import contacts
from conftest import load
from conftest import load_mjmodel

import mujoco
import mjx_supportfield as sf
from mjx_supportfield.geometry import faceclip
from mjx_supportfield.geometry import multicontact
from mjx_supportfield.geometry.mpr import BEHIND
from mjx_supportfield.geometry.mpr import mpr_funcs
from mjx_supportfield.stages import multicontact_pass
from mjx_supportfield.stages import narrowphase
from mjx_supportfield.types import SUPPORT_REFINED
from mjx_supportfield.types import MeshSupport

_TILTS = multicontact.tilt_funcs(SUPPORT_REFINED)
_MPR = mpr_funcs(SUPPORT_REFINED)

# the test kernels are only run forward: no adjoint code to build (on CUDA it would take minutes)
wp.set_module_options({"enable_backward": False})

CUBE = "-.05 -.05 -.05 .05 -.05 -.05 -.05 .05 -.05 .05 .05 -.05 -.05 -.05 .05 .05 -.05 .05 -.05 .05 .05 .05 .05 .05"
XML = f"""
<mujoco>
  <asset><mesh name="cube" vertex="{CUBE}"/></asset>
  <worldbody>
    <body pos="0 0 0.05"><freejoint/><geom name="lo" type="mesh" mesh="cube"/></body>
    <body pos="0.01 0.02 0.149" euler="0 0 20"><freejoint/><geom name="hi" type="mesh" mesh="cube"/></body>
    <body pos="1 0 0.05"><freejoint/><geom name="base" type="box" size=".05 .05 .05"/></body>
    <body pos="1 0 0.139"><freejoint/><geom name="cyl" type="cylinder" size=".03 .04"/></body>
    <body pos="2 0 0.05"><freejoint/><geom name="blk" type="box" size=".05 .05 .05"/></body>
    <body pos="2 0 0.129"><freejoint/><geom name="ball" type="ellipsoid" size=".03 .03 .03"/></body>
  </worldbody>
</mujoco>
"""


@pytest.fixture(scope="module")
def result():
  out = {}
  for multi in (True, False):
    sim = load(XML)
    sf.install(sim.mjm, sim.m, sf.Options(multi_contact=multi))
    sf.collision(sim.m, sim.d)
    out[multi] = (sim, contacts(sim.d, 0))
  return out


def _pair(sim, c, a, b):
  ga = mujoco.mj_name2id(sim.mjm, mujoco.mjtObj.mjOBJ_GEOM, a)
  gb = mujoco.mj_name2id(sim.mjm, mujoco.mjtObj.mjOBJ_GEOM, b)
  sel = [i for i in range(c.n) if set(c.geom[i]) == {ga, gb}]
  return c.dist[sel], c.pos[sel], c.normal[sel]


def test_face_on_face_spans_the_patch(result):
  sim, c = result[True]
  dist, pos, normal = _pair(sim, c, "lo", "hi")
  assert 4 <= len(dist) <= 5
  np.testing.assert_allclose(dist, -0.001, atol=1e-5)
  assert np.all(np.abs(normal[:, 2]) > 0.9999)
  # every point inside the overlap of the two squares (the lower cube's top face bounds it)
  assert np.all(np.abs(pos[:, :2]) <= 0.05 + 1e-4)
  # spread: the points span most of the patch, not one spot
  span = pos[:, :2].max(axis=0) - pos[:, :2].min(axis=0)
  assert np.all(span > 0.05), span


def test_cylinder_end_on_box_rim_points(result):
  """The largest quadrilateral of the end's 16-gon, and the deepest corner when it is not one
  of the four (all are as deep: the first corner): four or five points on the rim, around the
  axis."""
  sim, c = result[True]
  dist, pos, _ = _pair(sim, c, "base", "cyl")
  assert 4 <= len(dist) <= 5
  np.testing.assert_allclose(dist, -0.001, atol=1e-5)
  radial = np.linalg.norm(pos[:, :2] - [1.0, 0.0], axis=1)
  np.testing.assert_allclose(radial, 0.03, atol=1e-5)  # corners of the 16-gon lie on the rim
  angles = np.sort(np.degrees(np.arctan2(pos[:, 1], pos[:, 0] - 1.0)))
  assert np.diff(np.append(angles, angles[0] + 360.0)).max() <= 112.5 + 1e-3, angles


def test_round_shapes_keep_one_point(result):
  sim, c = result[True]
  dist, _, _ = _pair(sim, c, "blk", "ball")
  assert len(dist) == 1
  assert dist[0] == pytest.approx(-0.001, abs=1e-5)


def test_off_gives_one_point_per_pair(result):
  sim, c = result[False]
  for a, b in (("lo", "hi"), ("base", "cyl"), ("blk", "ball")):
    assert len(_pair(sim, c, a, b)[0]) == 1


STACK_XML = f"""
<mujoco>
  <option timestep="0.002"/>
  <asset><mesh name="cube" vertex="{CUBE}"/></asset>
  <worldbody>
    <geom name="floor" type="plane" size="2 2 .1"/>
    <body pos="0 0 0.0495"><freejoint/><geom name="lo" type="mesh" mesh="cube"/></body>
    <body pos="0.01 0.02 0.1485" euler="0 0 20"><freejoint/><geom name="hi" type="mesh" mesh="cube"/></body>
    <body pos="1 0 0.0495"><freejoint/><geom name="base" type="box" size=".05 .05 .05"/></body>
    <body pos="1 0 0.1385"><freejoint/><geom name="cyl" type="cylinder" size=".03 .04"/></body>
  </worldbody>
</mujoco>
"""


@pytest.mark.slow
@pytest.mark.parametrize("multi", [True, False])
def test_stacked_meshes_rest(multi):
  """A mesh cube on a mesh cube and a cylinder on a box, stepped through mjw.step: with
  multi-contact they stay put; one point per pair lets the top cube rock and sink."""
  import mujoco_warp as mjw

  sim = load(STACK_XML)
  sf.install(sim.mjm, sim.m, sf.Options(multi_contact=multi))
  d = mjw.make_data(sim.mjm, nworld=1, nconmax=64, njmax=400)
  for _ in range(100):
    mjw.step(sim.m, d)
  q0 = d.qpos.numpy()[0].copy()
  for _ in range(900):
    mjw.step(sim.m, d)
  q = d.qpos.numpy()[0]
  assert not np.isnan(q).any()
  cube, cyl = np.linalg.norm(q[7:10] - q0[7:10]), np.linalg.norm(q[21:24] - q0[21:24])
  if multi:
    assert cube < 2e-4 and cyl < 2e-5, (cube, cyl)
  else:
    assert cube > 1e-3  # documents why multi-contact is on by default



SLANT_XML = f"""
<mujoco>
  <asset><mesh name="cube" vertex="{CUBE}"/></asset>
  <worldbody>
    <body pos="0 0 0.05"><freejoint/><geom name="lo" type="mesh" mesh="cube"/></body>
    <body pos="0.01 0.02 {{z}}" axisangle="1 0.4 0 {{deg}}"><freejoint/><geom name="hi" type="mesh" mesh="cube"/></body>
  </worldbody>
</mujoco>
"""


@pytest.mark.parametrize("deg", [0.5, 1.5, 3.0, 4.5])
@pytest.mark.parametrize("z", [0.1505, 0.1495])
def test_slanted_faces_match_mujoco(deg, z):
  """A cube slanted a few degrees on another: MuJoCo C's multi-CCD writes one to four points
  (corner, edge or face contact, by angle and depth); the plugin writes as many, at the same
  depths (its tilt retries 9x steeper when the first tilt lands back on the same corner)."""
  sim = load(SLANT_XML.replace("{deg}", str(deg)).replace("{z}", str(z)))
  sf.install(sim.mjm, sim.m)
  sf.collision(sim.m, sim.d)
  dist, pos, _ = _pair(sim, contacts(sim.d, 0), "lo", "hi")
  mujoco.mj_forward(sim.mjm, sim.mjd)
  ref = np.sort([sim.mjd.contact[i].dist for i in range(sim.mjd.ncon)])
  assert len(dist) == len(ref), (dist, ref)
  np.testing.assert_allclose(np.sort(dist), ref, atol=3e-5)
  assert np.all(np.abs(pos[:, :2]) <= 0.05 + 1e-3) and np.all(np.abs(pos[:, 2] - 0.1) <= 0.01)


SUNK_XML = f"""
<mujoco>
  <asset><mesh name="cube" vertex="{CUBE}"/></asset>
  <worldbody>
    <body pos="0 0 0.05" euler="0 0 15"><freejoint/><geom name="block" type="mesh" mesh="cube"/></body>
    <body pos="{{x}} {{y}} {{z}}"><freejoint/><geom name="small" type="{{kind}}" size=".002 .003" euler="40 10 0"/></body>
  </worldbody>
</mujoco>
"""


@pytest.mark.parametrize("kind", ["sphere", "capsule"])
@pytest.mark.parametrize("where", [(0.03, 0.02, 0.097), (-0.035, 0.01, 0.094), (0.02, -0.041, 0.06)])
def test_small_geom_sunk_in_mesh_matches_mujoco(kind, where):
  """A 2 mm sphere or capsule sunk a few mm into a mesh block, off its centre: the nearest face
  decides the normal. The plugin takes these pairs through GJK/EPA on the sphere's point or the
  capsule's segment, so normal and depth match MuJoCo C's (MPR's ray from the centres made
  the normal drift by up to 58 degrees on aloha_pot's finger spheres)."""
  x, y, z = where
  sim = load(SUNK_XML.replace("{x}", str(x)).replace("{y}", str(y)).replace("{z}", str(z)).replace("{kind}", kind))
  sf.install(sim.mjm, sim.m)
  sf.collision(sim.m, sim.d)
  block = sim.mjm.geom("block").id
  c = contacts(sim.d, 0)
  assert c.n >= 1
  k = int(np.argmin(c.dist))
  normal = c.normal[k] * (1 if c.geom[k][0] == block else -1)  # from the block to the small geom
  mujoco.mj_forward(sim.mjm, sim.mjd)
  ref = sim.mjd.contact[int(np.argmin([sim.mjd.contact[i].dist for i in range(sim.mjd.ncon)]))]
  ref_normal = ref.frame[:3] * (1 if ref.geom[0] == block else -1)
  assert c.dist[k] == pytest.approx(ref.dist, abs=2e-5)
  assert np.degrees(np.arccos(np.clip(np.dot(normal, ref_normal), -1, 1))) < 1.0


CROSS_XML = """
<mujoco>
  <asset><mesh name="bar" vertex="-.1 -.01 -.01 .1 -.01 -.01 -.1 .01 -.01 .1 .01 -.01 -.1 -.01 .01 .1 -.01 .01 -.1 .01 .01 .1 .01 .01"/></asset>
  <worldbody>
    <body pos="0 0 0" euler="45 0 0"><freejoint/><geom name="lower" type="mesh" mesh="bar"/></body>
    <body pos="0 0 0.0280" euler="0 45 90"><freejoint/><geom name="upper" type="mesh" mesh="bar"/></body>
  </worldbody>
</mujoco>
"""

# two cylinders lying side by side along x, one on the other: a line contact of curved sides
ROLLERS_XML = """
<mujoco>
  <worldbody>
    <body pos="0 0 0" euler="0 90 0"><freejoint/><geom name="lower" type="cylinder" size=".02 .05"/></body>
    <body pos="0 0.005 0.0389" euler="0 90 0"><freejoint/><geom name="upper" type="cylinder" size=".02 .04"/></body>
  </worldbody>
</mujoco>
"""

# a 48-gon prism standing on a box: its end and the box's face have more corners together than
# face clipping takes on (faceclip.FACE_PAIR_BUDGET corner pairs)
PRISM_SIDES = 176  # a 176-gon end on a box's face: 176 x 4 corner pairs, over faceclip.FACE_PAIR_BUDGET
_ANGLES = np.arange(PRISM_SIDES) * 2.0 * np.pi / PRISM_SIDES
PRISM = " ".join(f"{0.03 * np.cos(t):.6f} {0.03 * np.sin(t):.6f} {z}" for z in (-0.02, 0.02) for t in _ANGLES)
PRISM_XML = f"""
<mujoco>
  <asset><mesh name="prism" vertex="{PRISM}"/></asset>
  <worldbody>
    <geom name="table" type="box" size=".1 .1 .05"/>
    <body pos="0 0 0.069"><freejoint/><geom name="prism" type="mesh" mesh="prism"/></body>
  </worldbody>
</mujoco>
"""


def _queues(src, nworld=1):
  """After one collision: the pairs queued for multi-contact, those left to the tilts, the sim."""
  sim = load(src, nworld=nworld)
  sf.install(sim.mjm, sim.m)
  sf.collision(sim.m, sim.d)
  st = sf.get_collider(sim.m).state(sim.m, sim.d).narrow
  return int(st.patch_count.numpy()[0]), int(st.tilt_pair_count.numpy()[0]), sim


def test_face_contacts_skip_the_tilts():
  """The face contacts (a cube on a cube, a cylinder's end on a box) are clipped: no pair of
  theirs reaches the tilt kernels. Crossed bars (edge on edge) and rollers (curved sides) have no
  face along the normal and go to the tilts."""
  assert _queues(XML)[:2] == (2, 0)
  assert _queues(CROSS_XML)[:2] == (1, 1)
  assert _queues(ROLLERS_XML)[:2] == (1, 1)


def test_polygons_over_the_budget_go_to_the_tilts():
  """A 176-gon end on a box's face (over faceclip.FACE_PAIR_BUDGET): the pair goes to the tilts,
  which still spread points over the end's rim, at the depth."""
  assert faceclip.FACE_PAIR_BUDGET < PRISM_SIDES * 4
  npatch, ntilt, sim = _queues(PRISM_XML)
  assert (npatch, ntilt) == (1, 1)
  c = contacts(sim.d, 0)
  assert c.n >= 3
  np.testing.assert_allclose(c.dist, -0.001, atol=2e-5)
  radial = np.linalg.norm(c.pos[:, :2], axis=1)
  assert np.all(radial > 0.029), radial


SCENES = {"crossed": CROSS_XML, "rollers": ROLLERS_XML}


@pytest.mark.parametrize("scene", list(SCENES))
@pytest.mark.parametrize("per_world", [0, 1])
def test_parallel_tilts_match_the_sequential_ones(monkeypatch, scene, per_world):
  """The tilts' MPRs (both attempts) run in their own threads (tilt_kernel) for up to a set
  number of pairs per world left to the tilts, the rest in patch_kernel's thread: both give the
  same contacts, bit for bit (room for every pair, for one, for none). Crossed bars and
  rollers: no face lies along the normal, so their pairs take the tilts."""

  def run():
    sim = load(SCENES[scene], nworld=2)
    sf.install(sim.mjm, sim.m)
    sf.collision(sim.m, sim.d)
    assert int(sf.get_collider(sim.m).state(sim.m, sim.d).narrow.tilt_pair_count.numpy()[0]) == 2
    n = int(sim.d.nacon.numpy()[0])
    c = sim.d.contact
    rows = np.concatenate([c.worldid.numpy()[:n, None], c.geom.numpy()[:n], c.dist.numpy()[:n, None],
                           c.pos.numpy()[:n], c.frame.numpy()[:n].reshape(n, 9)], axis=1)
    key = np.round(rows, 5)  # the order may not hang on the last bits the GPU leaves (below)
    return rows[np.lexsort(key.T[::-1])]

  parallel = run()
  monkeypatch.setattr(narrowphase, "TILT_PAIRS_PER_WORLD", per_world)
  fewer = run()
  assert len(parallel) >= 2 * (2 if scene == "rollers" else 1)
  if wp.get_device().is_cuda:
    # the same device functions compiled into two kernels: the CUDA compiler fuses their
    # multiply-adds differently, so the two agree to float32 rounding, not bit for bit
    np.testing.assert_allclose(fewer, parallel, rtol=1e-5, atol=1e-7)
  else:
    np.testing.assert_array_equal(fewer, parallel)


@wp.kernel
def _both_tilts(
  geom_type: wp.array(dtype=int), geom_dataid: wp.array2d(dtype=int), geom_size: wp.array2d(dtype=wp.vec3),
  geom_rbound: wp.array2d(dtype=float), geom_margin: wp.array2d(dtype=float), geom_gap: wp.array2d(dtype=float),
  pair_margin: wp.array2d(dtype=float), pair_gap: wp.array2d(dtype=float), geom_xpos: wp.array2d(dtype=wp.vec3),
  geom_xmat: wp.array2d(dtype=wp.mat33), ms: MeshSupport, eps: float, pair: wp.array(dtype=wp.vec2i),
  pairid: wp.array(dtype=wp.vec2i), pair_worldid: wp.array(dtype=int), patch_pair: wp.array(dtype=int),
  patch_result: wp.array(dtype=wp.vec4), patch_pos: wp.array(dtype=wp.vec3), closed: wp.array2d(dtype=wp.vec4),
  by_mpr: wp.array2d(dtype=wp.vec4),
):
  i, j = wp.tid()
  a, b, scale, res, rot = multicontact_pass._queued_tilt(geom_type, geom_dataid, geom_size, geom_rbound, geom_margin, geom_gap,
                                                   pair_margin, pair_gap, geom_xpos, geom_xmat, ms, eps, pair, pairid,
                                                   pair_worldid, patch_pair, patch_result, patch_pos, i, j)
  closed[i, j] = _TILTS.tilt_closed_form(a, b, ms, res, scale, rot)
  # the reference: the tilted MPR run to convergence (tilt_mpr stops at TILT_ITERATIONS)
  tilted = multicontact._tilted(a, res.pos, rot)
  q0 = _MPR.behind_origin(tilted, b, ms, res.normal, res.depth, scale, BEHIND)
  r = _MPR.mpr(tilted, b, ms, q0, scale, 1.0e-7, 500)
  by_mpr[i, j] = wp.vec4(0.0, 0.0, 0.0, multicontact.MISSED)
  if r.hit != 0:
    by_mpr[i, j] = multicontact._mapped_back(res, rot, r.pos + 0.5 * r.depth * r.normal, r.pos - 0.5 * r.depth * r.normal)


def _tilts_both_ways(sim):
  """Closed-form and MPR answers of every tilt of the pairs queued for multi-contact (one collision)."""
  sf.install(sim.mjm, sim.m)
  sf.collision(sim.m, sim.d)
  col = sf.get_collider(sim.m)
  st = col.state(sim.m, sim.d)
  pairs, st = st.broad, st.narrow
  npatch = int(st.patch_count.numpy()[0])
  closed = wp.zeros((npatch, 8), dtype=wp.vec4)
  by_mpr = wp.zeros((npatch, 8), dtype=wp.vec4)
  m, d = sim.m, sim.d
  wp.launch(_both_tilts, dim=(npatch, 8),
            inputs=[m.geom_type, m.geom_dataid, m.geom_size, m.geom_rbound, m.geom_margin, m.geom_gap, m.pair_margin,
                    m.pair_gap, d.geom_xpos, d.geom_xmat, col.mesh_support, col.options.mc_perturbation, pairs.pair,
                    pairs.pairid, pairs.pair_worldid, st.patch_pair, st.patch_result, st.patch_pos],
            outputs=[closed, by_mpr])
  types = sim.mjm.geom_type[pairs.pair.numpy()[st.patch_pair.numpy()[:npatch]]]
  flat = np.all((types == mujoco.mjtGeom.mjGEOM_BOX) | (types == mujoco.mjtGeom.mjGEOM_MESH), axis=1)
  return closed.numpy(), by_mpr.numpy(), flat


def _settled(name, steps=300):
  mjm = load_mjmodel(name)
  mjd = mujoco.MjData(mjm)
  for _ in range(steps):
    mujoco.mj_step(mjm, mjd)
  return load(None, mjm=mjm, qpos=mjd.qpos)


@pytest.mark.parametrize("scene", ["patches", "slanted", "convex_pile", "crossed"])
def test_closed_form_tilts_match_the_tilted_mpr(scene):
  """A tilt answered in closed form (a vertex of one shape through a flat face of the other)
  gives the converged tilted MPR's point and depth; the rest are left to MPR. The face
  contacts of the cube pair and the cylinder's end on the box need MPR only where a tilt
  dips a corner over the other's edge; crossed bars touch edge on edge, which the closed form
  must not answer. On a cylinder's rim MPR's point is only as good as its tolerance on the
  curve (0.14 mm off the rim here), the closed form's is the rim's support point
  (test_cylinder_end_on_box_rim_points)."""
  sim = {"patches": lambda: load(XML), "slanted": lambda: load(SLANT_XML.replace("{deg}", "3.0").replace("{z}", "0.1495")),
         "crossed": lambda: load(CROSS_XML),
         "convex_pile": lambda: _settled("convex_pile")}[scene]()
  closed, by_mpr, flat = _tilts_both_ways(sim)
  assert len(closed) > 0
  known = closed[..., 3] != multicontact.UNKNOWN
  missed = closed[..., 3] == multicontact.MISSED
  assert np.all(by_mpr[known & missed, 3] == multicontact.MISSED)
  hit = known & ~missed
  np.testing.assert_allclose(closed[hit & flat[:, None]], by_mpr[hit & flat[:, None]], atol=2e-6)
  curved = hit & ~flat[:, None]
  np.testing.assert_allclose(closed[curved][:, 3], by_mpr[curved][:, 3], atol=2e-6)
  np.testing.assert_allclose(closed[curved][:, :3], by_mpr[curved][:, :3], atol=5e-4)
  if scene == "patches":
    assert known[0].sum() >= 6 and known[1].all()  # the cubes' overhanging corner: edge on edge
  elif scene == "crossed":
    assert not known[..., :4].any()  # the first attempts stay on the crossing: edge on edge
  else:
    assert known.mean() > 0.2, known.mean()
