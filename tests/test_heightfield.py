"""Heightfields: flat terrain acts as a plane, slopes and ridges give the analytic contact, a
geom over many cells is found, bad grids are rejected, and nothing falls through bumpy terrain."""

import os
import sys

import mujoco
import mujoco_warp as mjw
import numpy as np
import pytest
from conftest import MODELS
from conftest import ROOT
from conftest import angle_deg
from conftest import contacts
from conftest import load
from conftest import printed
from conftest import set_qpos
from conftest import sorted_rows
from conftest import world_contact_fields

import mjx_supportfield as sf
from mjx_supportfield.stages import heightfield

sys.path.insert(0, MODELS)
import make_terrain  # noqa: E402


def _hfield_xml(elevation: np.ndarray, size, bodies: str) -> str:
  nrow, ncol = elevation.shape
  return f"""<mujoco><asset><hfield name="h" nrow="{nrow}" ncol="{ncol}" size="{' '.join(map(str, size))}"
    elevation="{' '.join(f'{v:.6f}' for v in elevation.ravel())}"/></asset>
    <worldbody><geom name="terrain" type="hfield" hfield="h"/>{bodies}</worldbody></mujoco>"""


def _plugin_contacts(xml: str):
  sim = load(xml)
  sf.install(sim.mjm, sim.m)
  sf.collision(sim.m, sim.d)
  return sim, contacts(sim.d, 0)


def _sorted(pos):
  return pos[np.lexsort(np.round(pos, 5).T)]


BOX = '<body pos="0.03 -0.02 0.0195" euler="0 0 20"><freejoint/><geom name="box" type="box" size=".06 .04 .02"/></body>'


@pytest.mark.parametrize("n", [9, 65])
def test_flat_terrain_gives_the_plane_contacts(n):
  """A box on flat terrain (coarse: the box inside one cell; fine: over ~100 cells) touches
  at MuJoCo's plane-box points."""
  _, hf = _plugin_contacts(_hfield_xml(np.zeros((n, n)), (0.5, 0.5, 0.1, 0.1), BOX))
  plane = load(f'<mujoco><worldbody><geom type="plane" size="1 1 .1"/>{BOX}</worldbody></mujoco>')
  ref = plane.mjd.contact[: plane.mjd.ncon]
  assert hf.n == len(ref) == 4
  np.testing.assert_allclose(_sorted(hf.pos), _sorted(np.array([c.pos for c in ref])), atol=1e-5)
  np.testing.assert_allclose(hf.dist, [c.dist for c in ref], atol=1e-6)
  np.testing.assert_allclose(hf.normal, np.tile([0.0, 0.0, 1.0], (4, 1)), atol=1e-6)


def test_sphere_on_slope_gets_the_analytic_normal():
  x = np.linspace(-1.0, 1.0, 5)
  z = 0.25 * (x + 1.0)  # z = 0.25 (x + 1): a plane, heights normalised by size[2] = 0.5
  normal = np.array([-0.25, 0.0, 1.0]) / np.linalg.norm([-0.25, 0.0, 1.0])
  r, depth = 0.1, 0.01
  centre = np.array([0.13, 0.07, 0.25 * 1.13]) + (r - depth) * normal
  ball = f'<body pos="{centre[0]} {centre[1]} {centre[2]}"><freejoint/><geom type="sphere" size="{r}"/></body>'
  sim, c = _plugin_contacts(_hfield_xml(np.tile(z / 0.5, (5, 1)), (1, 1, 0.5, 0.1), ball))
  # MuJoCo C's contacts: the analytic one, and where the ball reaches over the corner of the
  # next cell's triangle a shallow one of that prism (its normal tilted 26 deg toward the
  # corner). The plugin gives both points, each along the slope's normal
  ref = sim.mjd.contact[: sim.mjd.ncon]
  assert c.n == len(ref) == 2
  for pos in ref.pos:
    assert np.linalg.norm(c.pos - pos, axis=1).min() < 1e-4
  for k in range(c.n):
    assert angle_deg(c.normal[k], normal) < 0.01
  assert abs(-c.dist.min() - depth) < 1e-6


def test_capsule_across_a_slope_in_closed_form():
  """A capsule the size of a G1 foot's (1 cm radius, 18 cm between its ends) lying 1 mm deep
  along a plane slope, across cells and their diagonals: the closed-form pass (no MPR job: none
  left beyond a queue of one) gives the slope's normal and depth at every contact, from one end
  of the capsule to the other, and no contact beside it on the triangles' flat edges."""
  x = np.linspace(-1.0, 1.0, 21)  # 10 cm cells
  z = 0.25 * (x + 1.0)
  normal = np.array([-0.25, 0.0, 1.0]) / np.linalg.norm([-0.25, 0.0, 1.0])
  along = np.array([1.0, 0.0, 0.25]) / np.linalg.norm([1.0, 0.0, 0.25])
  r, half, depth = 0.01, 0.09, 0.001
  centre = np.array([0.03, 0.02, 0.25 * 1.03]) + (r - depth) * normal
  capsule = (f'<body pos="{centre[0]} {centre[1]} {centre[2]}"><freejoint/><geom type="capsule" size="{r} {half}" '
             f'zaxis="{along[0]} {along[1]} {along[2]}"/></body>')
  sim = load(_hfield_xml(np.tile(z / 0.5, (21, 1)), (1, 1, 0.5, 0.1), capsule))
  collider = sf.install(sim.mjm, sim.m, sf.Options(hfield_mprs_per_pair=1))
  sf.collision(sim.m, sim.d)
  c = contacts(sim.d, 0)
  assert collider.stats(sim.d)["hfield_mprs_unqueued"] == 0
  assert c.n >= 2
  for k in range(c.n):
    assert angle_deg(c.normal[k], normal) < 0.01
    assert abs(-c.dist[k] - depth) < 1e-5
  ends = [centre + s * half * along - (r - depth / 2) * normal for s in (-1.0, 1.0)]
  for end in ends:
    assert np.linalg.norm(c.pos - end, axis=1).min() < 1e-4, (end, c.pos)


@pytest.mark.parametrize("case, nsurface, deepest", [("hfield_sunk_capsule", 2, 0.011),
                                                     ("hfield_capsule_off_footprint", 4, 0.003)])
def test_foot_capsule_gets_mujocos_prism_answers(case, nsurface, deepest):
  """G1 foot capsules (1 cm radius) on patches of humanoid_rough's terrain (tests/data/repro):
  sunk 15 mm, its axis below the slope it lies across, where the least overlap with a triangle's
  prism lies across one of the triangle's edges, not along its normal; and lying 3 mm deep across
  a fold, where the capsule's point nearest to a sloped triangle lies past the triangle's edge
  seen along z. Each of MuJoCo C's contacts but those through a wall between two prisms (a
  horizontal normal inside the grid) has the plugin's contact at its point, along its normal and
  as deep."""
  with open(os.path.join(ROOT, "tests", "data", "repro", f"{case}.xml")) as f:
    sim, c = _plugin_contacts(f.read())
  ref = sim.mjd.contact[: sim.mjd.ncon]
  surface = [k for k in range(len(ref)) if abs(ref.frame[k][2]) > 1e-3]
  assert len(surface) == nsurface and min(ref.dist) < -deepest
  for k in surface:
    near = int(np.argmin(np.linalg.norm(c.pos - ref.pos[k], axis=1)))
    assert np.linalg.norm(c.pos[near] - ref.pos[k]) < 1e-4, (ref.pos[k], c.pos)
    assert angle_deg(c.normal[near], ref.frame[k][:3]) < 0.1
    assert abs(c.dist[near] - ref.dist[k]) < 1e-5


def test_ridge_poking_into_a_sphere():
  """A sphere over a roof ridge touches only the ridge edge: no triangle's plane sees it."""
  x = np.linspace(-1.0, 1.0, 5)
  roof = np.tile(1.0 - np.abs(x), (5, 1))  # ridge along y at x = 0, height 0.5 * 1
  r, depth = 0.05, 0.002
  ball = f'<body pos="0 0.1 {0.5 + r - depth}"><freejoint/><geom type="sphere" size="{r}"/></body>'
  _, c = _plugin_contacts(_hfield_xml(roof, (1, 1, 0.5, 0.1), ball))
  assert c.n >= 1
  deepest = int(np.argmin(c.dist))
  assert angle_deg(c.normal[deepest], [0, 0, 1]) < 0.5
  assert abs(-c.dist[deepest] - depth) < 1e-5
  np.testing.assert_allclose(c.pos[deepest][:2], [0.0, 0.1], atol=1e-4)


def test_small_box_across_a_coarse_ridge():
  """A box smaller than a cell lying across the ridge edge, its corners in the air."""
  x = np.linspace(-1.0, 1.0, 3)
  roof = np.tile(1.0 - np.abs(x), (3, 1))  # one ridge at x = 0, cells 1 m wide
  box = '<body pos="0 0.2 0.519" euler="0 0 0"><freejoint/><geom type="box" size=".04 .04 .02"/></body>'
  _, c = _plugin_contacts(_hfield_xml(roof, (1, 1, 0.5, 0.1), box))
  assert c.n >= 1
  assert np.all(np.abs(c.pos[:, 0]) < 1e-3)  # on the ridge line
  np.testing.assert_allclose(-c.dist.max(), 0.001, atol=1e-5)  # the box bottom is 1 mm below the ridge top
  assert np.all(c.normal[:, 2] > 0.999)


def _box_on_bumps():
  """A 32 cm box face lying on a slope (z = 0.1 x) 4.5 mm above it, over nine bumps of 5.5 to
  8.5 mm on the grid vertices under it (cells of 10 cm): each bump pokes 1 to 4 mm into the face.
  Returns the MJCF, the heights, the bumps' apexes and depths, a point of the face and its normal."""
  x = np.linspace(-0.4, 0.4, 9)
  height = np.tile(0.1 * x, (9, 1))
  height[3:6, 3:6] += 1e-3 * (5.5 + 0.375 * np.array([[3, 7, 1], [5, 8, 0], [2, 6, 4]]))
  base = height.min()
  height -= base
  normal = np.array([-0.1, 0.0, 1.0]) / np.linalg.norm([-0.1, 0.0, 1.0])
  face = np.array([0.0, 0.0, -base]) + 0.0045 * normal
  centre = face + 0.02 * normal
  box = (f'<body pos="{centre[0]} {centre[1]} {centre[2]}" euler="0 {-np.degrees(np.arctan(0.1))} 0"><freejoint/>'
         '<geom name="box" type="box" size=".16 .16 .02"/></body>')
  apex = np.array([[x[c], x[r], height[r, c]] for r in range(3, 6) for c in range(3, 6)])
  # MuJoCo reads the elevation's first row as the grid's last (at y = +size[1])
  xml = _hfield_xml(np.flipud(height) / height.max(), (0.4, 0.4, height.max(), 0.1), box)
  return xml, height, apex, (apex - face) @ normal, face, normal


def test_box_on_bumps_touches_every_bump():
  """A box face on rough terrain rests on every bump that pokes into it: a contact at each of the
  nine (halfway between the apex and the face, as deep as the apex, along the face's normal), as
  MuJoCo C's prisms find them, not only the five spread widest; the other contacts are points of
  the bumps' slopes inside the box (one a prism, as MuJoCo C's GJK/EPA gives them, along the
  slope's normal); every contact a terrain point inside the box at its own depth, none two at one
  place, and no more of them than MuJoCo C writes."""
  xml, height, apex, depth, face, normal = _box_on_bumps()
  assert np.all(depth > 0.0009) and np.all(depth < 0.0041)
  # MuJoCo C's prisms find these depths too (with libccd's MPR: its default EPA stops short on
  # this scene, with shallower points away from the bumps)
  mjm = mujoco.MjModel.from_xml_string(xml)
  mjm.opt.disableflags |= mujoco.mjtDisableBit.mjDSBL_NATIVECCD
  mjd = mujoco.MjData(mjm)
  mujoco.mj_forward(mjm, mjd)
  found = np.abs(-mjd.contact.dist[: mjd.ncon, None] - depth[None, :]) < 5e-5
  assert found.any(axis=1).all() and found.any(axis=0).all()
  sim, c = _plugin_contacts(xml)
  assert c.n <= sim.mjd.ncon  # MuJoCo C's default collision, one contact a prism
  on_terrain = c.pos - 0.5 * c.dist[:, None] * c.normal
  at_apex = np.zeros(c.n, bool)
  for p in apex:
    nearest = np.linalg.norm(on_terrain - p, axis=1)
    assert nearest.min() < 1e-3, (p, on_terrain)
    at_apex[np.argmin(nearest)] = True
  size = (0.4, 0.4, height.max())
  for i in range(c.n):
    assert abs(on_terrain[i, 2] - make_terrain.terrain_height(size, height / height.max(), *on_terrain[i, :2])) < 1e-5
    assert abs((on_terrain[i] - face) @ normal + c.dist[i]) < 1e-5
    # a bump's slopes lean at most 2.5 deg from the face
    assert angle_deg(c.normal[i], normal) < (0.01 if at_apex[i] else 2.5)
    assert np.min(np.delete(np.linalg.norm(c.pos - c.pos[i], axis=1), i)) > 0.003


# a rough patch of terrain (random elevations, kept as numbers)
ROUGH = np.array([
  0.9431, 0.5113, 0.9762, 0.0808, 0.6074, 0.3765, 0.8019, 0.1745,
  0.8716, 0.5439, 0.9022, 0.4772, 0.4305, 0.7889, 0.9842, 0.3697,
  0.9689, 0.9290, 0.1777, 0.6089, 0.7049, 0.9428, 0.6657, 0.1334,
  0.4979, 0.4936, 0.5002, 0.9586, 0.3499, 0.2238, 0.5221, 0.6412,
  0.9391, 0.5820, 0.2678, 0.9298, 0.4917, 0.6758, 0.4760, 0.2170,
  0.6926, 0.7706, 0.1908, 0.4599, 0.3618, 0.1707, 0.2214, 0.9625,
  0.8842, 0.3823, 0.7395, 0.0420, 0.9151, 0.5372, 0.8203, 0.2759,
  0.3761, 0.3480, 0.9724, 0.4295, 0.4997, 0.9560, 0.9032, 0.3950,
]).reshape(8, 8)


def test_ball_in_a_hollow_touches_every_triangle():
  """A ball (2 cm, 2 mm deep) in a hollow of rough terrain gets MuJoCo C's contacts, one for each
  triangle it touches (for a sphere C's are exact: each triangle's point nearest the centre),
  and no more: also the triangle it meets only at a concave edge, from over the next triangle
  (no point of that triangle's plane under the ball lies on it, and the edge is no ridge)."""
  ball = '<body pos="0.019846 0.007602 0.024571"><freejoint/><geom name="ball" type="sphere" size="0.02"/></body>'
  sim, c = _plugin_contacts(_hfield_xml(ROUGH, (0.0875, 0.0875, 0.02, 0.05), ball))
  ref = sim.mjd.contact[: sim.mjd.ncon]
  assert len(ref) == 5 and min(ref.dist) < -0.0019
  assert c.n == len(ref)
  for pos, dist, frame in zip(ref.pos, ref.dist, ref.frame):
    k = int(np.argmin(np.linalg.norm(c.pos - pos, axis=1)))
    assert np.linalg.norm(c.pos[k] - pos) < 1e-4, (pos, c.pos)
    assert abs(c.dist[k] - dist) < 2e-5
    assert angle_deg(c.normal[k], frame[:3]) < 1.0


# a frustum-shaped hull: a box-like face below, a smaller one above
FRUSTUM = "-.04 -.03 -.01 .04 -.03 -.01 .04 .03 -.01 -.04 .03 -.01 -.03 -.02 .01 .03 -.02 .01 .03 .02 .01 -.03 .02 .01"


def _jittered(qpos: np.ndarray, rng) -> np.ndarray:
  """A free body's qpos moved by about 1e-7 (m, and in its quaternion): float32 rounding, as a GPU's
  kinematics gives it beside the CPU's."""
  q = qpos.copy()
  q[:7] += rng.normal(size=7) * 1e-7
  q[3:7] /= np.linalg.norm(q[3:7])
  return q


@pytest.mark.parametrize("geom, x, y, yaw, tilt, sink", [
  ('type="box" size=".04 .03 .01"', 0.02, 0.02, 10, 5, 0.003),
  ('type="mesh" mesh="frustum"', -0.02, 0.01, 60, 0, 0.002),
])
def test_face_on_rough_terrain_covers_mujocos_points(geom, x, y, yaw, tilt, sink):
  """A box and a hull lying with a face on rough terrain, sunk 2-3 mm: each of MuJoCo C's contact
  points at least 0.5 mm deep (one a triangle prism, where its GJK/EPA ends, spread over the
  face) has a contact of the pair within 3 mm, as the prisms' own GJK/EPA gives them (the deepest
  terrain points alone left a third of them uncovered), and there are hardly more contacts than
  MuJoCo C writes. Where an EPA ends is ill-conditioned: for some prisms MuJoCo C's own point
  moves by millimetres when the pose moves by 1e-7, so only C's points that stay put under such
  jitter are asked for, and the plugin must cover them at each jittered pose too (a rounding
  difference, as between a GPU and the CPU, must not decide the test)."""
  size = (0.0875, 0.0875, 0.02, 0.05)
  under = [make_terrain.terrain_height(size[:3], ROUGH, x + dx, y + dy) for dx in np.linspace(-0.04, 0.04, 9)
           for dy in np.linspace(-0.04, 0.04, 9)]
  body = (f'<body pos="{x} {y} {max(under) + 0.01 - sink}" euler="{tilt} 0 {yaw}"><freejoint/>'
          f'<geom name="b" {geom}/></body>')
  xml = _hfield_xml(ROUGH, size, body).replace("</asset>", f'<mesh name="frustum" vertex="{FRUSTUM}"/></asset>')
  sim, c = _plugin_contacts(xml)
  ref = sim.mjd.contact[: sim.mjd.ncon]
  assert c.n <= len(ref) + 1
  rng = np.random.default_rng(0)
  poses = [sim.mjd.qpos.copy()] + [_jittered(sim.mjd.qpos, rng) for _ in range(4)]
  mjd = mujoco.MjData(sim.mjm)
  stable = ref.pos[ref.dist < -5e-4]
  for q in poses[1:]:
    mjd.qpos[:] = q
    mujoco.mj_forward(sim.mjm, mjd)
    moved = mjd.contact.pos[: mjd.ncon]
    stable = stable[[np.min(np.linalg.norm(moved - p, axis=1)) < 5e-4 for p in stable]]
  assert len(stable) >= 8
  for q in poses:
    set_qpos(sim, q)
    sf.collision(sim.m, sim.d)
    pos = contacts(sim.d, 0).pos
    for p in stable:
      assert np.min(np.linalg.norm(pos - p, axis=1)) < 3e-3, (q, p, pos)


def test_bad_heightfield_is_rejected():
  mjm = mujoco.MjModel.from_xml_string(_hfield_xml(np.zeros((3, 3)), (1, 1, 0.1, 0.1), BOX))
  m = mjw.put_model(mjm)
  mjm.hfield_ncol[0] = 1  # MuJoCo's compiler refuses such a grid; an edited model must be refused too
  with pytest.raises(ValueError, match="geom 'terrain'.*1 columns"):
    sf.install(mjm, m)
  with pytest.raises(ValueError, match="hfield dimensions"):
    mujoco.MjModel.from_xml_string(_hfield_xml(np.zeros((1, 3)), (1, 1, 0.1, 0.1), BOX))


def _surface_clearance(mjm, mjd):
  """Per body: height of its centre above the terrain surface below it."""
  data = mjm.hfield_data.reshape(mjm.hfield_nrow[0], mjm.hfield_ncol[0])
  return {mjm.body(b).name: mjd.xpos[b][2] - make_terrain.terrain_height(mjm.hfield_size[0], data, *mjd.xpos[b][:2])
          for b in range(1, mjm.nbody)}


STEPS = 2500


@pytest.fixture(scope="module")
def dropped():
  """models/terrain.xml stepped by the plugin through mjw.step (and MuJoCo C for reference): the
  simulation, each body's lowest clearance and the largest joint speed at each snapshot."""
  sim = load("terrain")
  sf.install(sim.mjm, sim.m)
  lowest, speeds = {}, []
  for i in range(STEPS):
    mjw.step(sim.m, sim.d)
    if i % 50 == 49:
      mjd = mujoco.MjData(sim.mjm)
      mjd.qpos[:] = sim.d.qpos.numpy()[0]
      mujoco.mj_kinematics(sim.mjm, mjd)
      for name, h in _surface_clearance(sim.mjm, mjd).items():
        lowest[name] = min(lowest.get(name, np.inf), h)
      speeds.append(float(np.abs(sim.d.qvel.numpy()).max()))
  return sim, lowest, speeds


def test_terrain_scene_matches_generator():
  with open(os.path.join(MODELS, "terrain.xml")) as f:
    assert f.read() == make_terrain.xml()


@pytest.mark.slow
def test_every_body_stays_on_the_terrain(dropped):
  sim, lowest, _ = dropped
  assert np.all(np.isfinite(sim.d.qpos.numpy()))
  assert set(lowest) == {b[0] for b in make_terrain.BODIES}
  for name, clearance in lowest.items():
    # centres never sink below the surface by more than a tenth of the smallest geom radius
    assert clearance > 0.0, (name, clearance)


def test_bodies_come_to_rest_on_it(dropped):
  """In the last second every body is still at once, at some snapshot. Not at one fixed instant:
  a body balanced on a bump may tip over late and roll into a hollow (MuJoCo C's own run of this
  scene is not still at 5 s either), and on a GPU the contact rows' order, hence the trajectory,
  differs from run to run. Contacts that never let the bodies settle fail it."""
  sim, _, speeds = dropped
  assert min(speeds[-10:]) < 0.1, speeds[-10:]
  assert int(sim.d.nacon.numpy()[0]) >= len(make_terrain.BODIES)


def test_geom_over_too_many_cells_reports_overflow(capfd):
  """A box over ~8000 cells (more than MAX_CELLS): the cells around its centre still give the
  contact, and the pair sets OverflowType.HFIELD with a warning, as MuJoCo Warp reports its own."""
  big = '<body pos="0 0 0.049"><freejoint/><geom name="slab" type="box" size=".35 .35 .05"/></body>'
  sim, c = _plugin_contacts(_hfield_xml(np.zeros((129, 129)), (0.5, 0.5, 0.1, 0.1), big))
  assert int(sim.d.overflow.numpy().max()) & int(mjw.OverflowType.HFIELD)
  assert "heightfield overflow" in printed(capfd)
  assert c.n >= 1
  np.testing.assert_allclose(c.dist, -0.001, atol=1e-5)
  np.testing.assert_allclose(c.normal[:, 2], 1.0, atol=1e-6)


def test_full_mpr_queue_gives_the_same_contacts(dropped):
  """Terrain MPRs that find their queue full run in their pair's thread: the bodies of
  models/terrain.xml at rest on its bumps (hundreds of MPRs for the geoms over many cells) get
  the same contacts with room for one MPR a pair as with room for all; the stats count them."""
  qpos = dropped[0].d.qpos.numpy()[0]
  found = {}
  for room in (4096, 1):
    sim = load("terrain", qpos=qpos)
    sf.install(sim.mjm, sim.m, sf.Options(hfield_mprs_per_pair=room))
    sf.collision(sim.m, sim.d)
    found[room] = world_contact_fields(sim.d, 0), sf.get_collider(sim.m).stats(sim.d)["hfield_mprs_unqueued"]
  (roomy, roomy_unqueued), (tight, tight_unqueued) = found[4096], found[1]
  assert roomy_unqueued == 0 and tight_unqueued > 100
  assert len(roomy["pos"]) == len(tight["pos"]) >= len(make_terrain.BODIES)
  # bit for bit, in a canonical order: on a GPU each contact takes its row by an atomic, so the
  # rows' order differs from run to run
  roomy, tight = sorted_rows(roomy), sorted_rows(tight)
  for field in roomy:
    np.testing.assert_array_equal(roomy[field], tight[field], err_msg=field)


def test_default_queue_holds_a_fine_grids_mprs(dropped):
  """The MPR queue's room is counted per pair of a geom other than a sphere or a capsule (those
  take MPRs only past the grid's edge: one in ROUND_PAIRS_PER_JOB_PAIR of theirs counts): with the
  default room, every MPR of models/terrain.xml's bodies at rest on its fine grid (hundreds a
  world) runs side by side from the queue, none one after another in its pair's thread."""
  sim = load("terrain", qpos=dropped[0].d.qpos.numpy()[0])
  collider = sf.install(sim.mjm, sim.m)
  sf.collision(sim.m, sim.d)
  assert collider.stats(sim.d)["hfield_mprs_unqueued"] == 0
  types = sim.mjm.geom_type[1:]  # every geom but the terrain meets it
  rounds = int(np.isin(types, [mujoco.mjtGeom.mjGEOM_SPHERE, mujoco.mjtGeom.mjGEOM_CAPSULE]).sum())
  job_pairs = len(types) - rounds + -(-rounds // heightfield.ROUND_PAIRS_PER_JOB_PAIR)
  queue = collider.state(sim.m, sim.d).hfield.job
  assert queue.shape[0] == sim.d.nworld * job_pairs * sf.Options().hfield_mprs_per_pair


def test_prisms_beyond_both_queues_are_counted(monkeypatch):
  """Box prisms beyond the MPR queue that find the beyond queue full too run MPR, and stats(d)
  counts them (hfield_ccd_as_mpr), so that the fallback is never silent: two boxes, one place in
  the beyond queue."""
  size = (0.0875, 0.0875, 0.02, 0.05)
  bodies = "".join(f'<body pos="{x} 0.02 0.028" euler="5 0 10"><freejoint/><geom type="box" size=".03 .02 .01"/></body>'
                   for x in (-0.04, 0.04))
  monkeypatch.setattr(heightfield, "CCD_BEYOND", 1)
  sim = load(_hfield_xml(ROUGH, size, bodies))
  collider = sf.install(sim.mjm, sim.m, sf.Options(hfield_mprs_per_pair=1))
  sf.collision(sim.m, sim.d)
  stats = collider.stats(sim.d)
  assert stats["hfield_mprs_unqueued"] > 0 and stats["hfield_ccd_as_mpr"] > 0
  assert "beyond both queues" in str(stats)
  assert contacts(sim.d, 0).n > 0



def _fill_with_garbage(arrays) -> None:
  """NaN in the float arrays, random integers in the others."""
  rng = np.random.default_rng(0)
  for a in arrays:
    x = a.numpy()
    x[...] = np.nan if x.dtype.kind == "f" else rng.integers(-2**31, 2**31 - 1, size=x.shape)
    a.assign(x)


def test_prism_contacts_need_nothing_of_the_epa_memory_before(dropped, monkeypatch):
  """Each GJK/EPA run writes its row of EPA memory before it reads it, and no answer depends on
  which row a prism gets: the terrain bodies' contacts (boxes and meshes, their prisms queued or
  beyond the queue) are bit for bit the same with the memory filled with NaN and garbage, and
  with one row for all of hfield_ccd's prisms, run one after another, as with a row for each.
  Two prisms on one row at once would clobber each other only on a GPU, whose threads run side
  by side; each thread's row is its own (its index in hfield_ccd, which runs the prisms beyond the
  queue too), and this checks the rest of that contract on the CPU."""
  qpos = dropped[0].d.qpos.numpy()[0]
  found = []
  for room in (4096, 1):
    sim = load("terrain", qpos=qpos)
    collider = sf.install(sim.mjm, sim.m, sf.Options(hfield_mprs_per_pair=room))
    sf.collision(sim.m, sim.d)
    found.append(sorted_rows(world_contact_fields(sim.d, 0)))
    _fill_with_garbage(collider.state(sim.m, sim.d).hfield.epa)
    sf.collision(sim.m, sim.d)
    found.append(sorted_rows(world_contact_fields(sim.d, 0)))
  monkeypatch.setattr(heightfield, "CCD_THREADS", 1)
  sim = load("terrain", qpos=qpos)
  collider = sf.install(sim.mjm, sim.m, sf.Options(hfield_mprs_per_pair=4096))  # every prism queued
  sf.collision(sim.m, sim.d)
  assert collider.state(sim.m, sim.d).hfield.ccd_rows == 1 and collider.stats(sim.d)["hfield_ccd_as_mpr"] == 0
  found.append(sorted_rows(world_contact_fields(sim.d, 0)))
  assert len(found[0]["pos"]) >= len(make_terrain.BODIES)
  for other in found[1:]:
    for field in found[0]:
      np.testing.assert_array_equal(found[0][field], other[field], err_msg=field)


def test_capsule_across_the_edge_is_pushed_out_through_the_border():
  """humanoid_rough's G1 torso capsule (radius 9 cm) toppled across the wave tile's outer edge
  (tests/data/repro/hfield_edge_capsule.xml): MuJoCo C pushes it out through the border prisms'
  side walls, 92 mm deep along -x. The plugin dropped every side-wall answer (inside the terrain
  between cells) and kept one contact 43 mm deep, and in the rollout let the capsule sink 113 mm
  where MuJoCo C and stock stop it at 25 mm; the outer walls' answers are now kept: the deepest
  contact of the pair within 10 % of MuJoCo C's."""
  mjm = mujoco.MjModel.from_xml_path(os.path.join(ROOT, "tests", "data", "repro", "hfield_edge_capsule.xml"))
  sim = load(None, mjm=mjm, naconmax=128)
  c_deepest = -min(c.dist for c in sim.mjd.contact[: sim.mjd.ncon])
  sf.install(mjm, sim.m)
  sf.collision(sim.m, sim.d)
  got = contacts(sim.d, 0)
  assert got.n > 0 and -got.dist.min() > 0.9 * c_deepest, (got.dist, c_deepest)


def test_terrain_point_contacts_stay_on_the_terrain():
  """models/real/humanoid_rough.xml's first state: the G1s' foot capsules (1 cm radius, 18.6 cm
  long) lie across several cells of the rough and wave tiles. MPR against a terrain point put a
  contact where B's support tie ends (a capsule's centre), cells from the point and up to 28 mm
  above the terrain. Every heightfield contact lies within compare's bound of the terrain
  (|dist| / 2 + 1 mm), on the plugin's second (warm-started) call as in a rollout."""
  from mjx_supportfield.tools import compare
  from mjx_supportfield.tools import exact
  from scenelib import real_scenes

  mjm = real_scenes.load("humanoid_rough")
  qpos = real_scenes.initial_data(mjm).qpos.copy()
  ref = compare.mujoco_reference(mjm, qpos)
  got = compare.warp_contacts(mjm, [qpos], plugin=sf.Options())[0]
  hfields = [g for g in range(mjm.ngeom) if mjm.geom_type[g] == mujoco.mjtGeom.mjGEOM_HFIELD]
  checked = 0
  for c in got:
    for g in set(c.geom) & set(hfields):
      local = ref.xmat[g].T @ (c.pos - ref.xpos[g])
      outside = exact.hfield_distance(mjm, int(mjm.geom_dataid[g]), local)
      assert outside <= abs(c.dist) / 2 + 1e-3, f"{c.geom}: {outside * 1e3:.1f} mm off the terrain"
      checked += 1
  assert checked > 20
