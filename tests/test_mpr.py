"""MPR through the full pipeline (kinematics -> broad phase -> narrow phase) on pairs with
analytic answers.

One model holds every pair, each pair in its own slot far from the others (positions set
through qpos). World 0 has every pair penetrating, world 1 the same pairs GAP apart: those
give no contact, except the pairs whose geoms have a margin larger than GAP, which must give
one contact at dist = +GAP.
"""

import zlib

import mujoco
import numpy as np
import pytest

import mjx_supportfield as sf
from conftest import angle_deg
from conftest import contacts
from conftest import free_body_qpos
from conftest import geom_id
from conftest import load
from conftest import quat_mat
from conftest import unit
from conftest import random_quat
from conftest import set_qpos

CUBE = " ".join(f"{x} {y} {z}" for x in (-0.05, 0.05) for y in (-0.05, 0.05) for z in (-0.05, 0.05))
MARGIN = 0.005
GAP = 0.002  # separation in world 1

XML = f"""
<mujoco model="mpr_pairs">
  <option gravity="0 0 0"/>
  <asset>
    <mesh name="cube" vertex="{CUBE}"/>
  </asset>
  <worldbody>
    <body name="ell_a"><freejoint/><geom name="ell_a" type="ellipsoid" size="0.05 0.05 0.05"/></body>
    <body name="ell_b"><freejoint/><geom name="ell_b" type="ellipsoid" size="0.05 0.05 0.05"/></body>
    <body name="ax_a"><freejoint/><geom name="ax_a" type="ellipsoid" size="0.04 0.04 0.04"/></body>
    <body name="ax_b"><freejoint/><geom name="ax_b" type="ellipsoid" size="0.04 0.04 0.04"/></body>
    <body name="sph"><freejoint/><geom name="sph" type="sphere" size="0.04"/></body>
    <body name="ell"><freejoint/><geom name="ell" type="ellipsoid" size="0.06 0.04 0.03"/></body>
    <body name="cyl"><freejoint/><geom name="cyl" type="cylinder" size="0.03 0.04"/></body>
    <body name="cylbase"><freejoint/><geom name="cylbase" type="box" size="0.1 0.08 0.05"/></body>
    <body name="mcube"><freejoint/><geom name="mcube" type="mesh" mesh="cube"/></body>
    <body name="mbase"><freejoint/><geom name="mbase" type="box" size="0.1 0.1 0.05"/></body>
    <body name="mlow"><freejoint/><geom name="mlow" type="mesh" mesh="cube"/></body>
    <body name="mhigh"><freejoint/><geom name="mhigh" type="mesh" mesh="cube"/></body>
    <body name="mg_a"><freejoint/><geom name="mg_a" type="ellipsoid" size="0.04 0.04 0.04" margin="{MARGIN}"/></body>
    <body name="mg_b"><freejoint/><geom name="mg_b" type="ellipsoid" size="0.04 0.04 0.04" margin="{MARGIN}"/></body>
    <body name="mgc_low"><freejoint/><geom name="mgc_low" type="box" size="0.1 0.1 0.05" margin="{MARGIN}"/></body>
    <body name="mgc_high"><freejoint/><geom name="mgc_high" type="mesh" mesh="cube" margin="{MARGIN}"/></body>
    <body name="gsph"><freejoint/><geom name="gsph" type="sphere" size="0.04"/></body>
    <body name="gell"><freejoint/><geom name="gell" type="ellipsoid" size="0.06 0.04 0.03"/></body>
  </worldbody>
</mujoco>
"""


def yaw(angle):
  return np.array([np.cos(angle / 2), 0.0, 0.0, np.sin(angle / 2)])


# Each case places its two bodies around a slot centre c for a signed separation sep (negative:
# penetration) and returns (geom1, geom2, normal from geom1 to geom2, contact midpoint, patch):
# patch is None for a point contact, else the radius of a disc around the midpoint's xy that
# holds the contact patch of a face contact. geom1 is the geom of lower type, or of lower id.


def spheres_oblique(mjm, qpos, c, sep, rng):
  u = unit([0.6, -0.48, 0.64])
  r = 0.05
  free_body_qpos(mjm, qpos, "ell_a", c, random_quat(rng))
  free_body_qpos(mjm, qpos, "ell_b", c + u * (2 * r + sep), random_quat(rng))
  return "ell_a", "ell_b", u, c + u * (r + sep / 2), None


def spheres_on_axis(mjm, qpos, c, sep, rng):
  # centres exactly on the x axis: MPR's first support lies on the centre line (degenerate path)
  r = 0.04
  free_body_qpos(mjm, qpos, "ax_a", c, [1, 0, 0, 0])
  free_body_qpos(mjm, qpos, "ax_b", c + np.array([2 * r + sep, 0, 0]), [1, 0, 0, 0])
  return "ax_a", "ax_b", np.array([1.0, 0, 0]), c + np.array([r + sep / 2, 0, 0]), None


def _sphere_on_ellipsoid(mjm, qpos, c, sep, rng, names, w_local):
  """Sphere touching a rotated ellipsoid at the surface point q(w) with outward normal n: the
  sphere centre q + n (r + sep) has q as its nearest ellipsoid point, so depth = -sep exactly."""
  sph, ell = names
  s = np.array([0.06, 0.04, 0.03])
  qe = random_quat(rng)
  rot = quat_mat(qe)
  q_local = s * unit(w_local)
  q = c + rot @ q_local
  n = unit(rot @ (q_local / s**2))
  r = 0.04
  free_body_qpos(mjm, qpos, ell, c, qe)
  free_body_qpos(mjm, qpos, sph, q + n * (r + sep), [1, 0, 0, 0])
  # geom1 is the sphere (lower geom type): the normal points from the sphere into the ellipsoid
  return sph, ell, -n, q + n * sep / 2, None


def sphere_ellipsoid(mjm, qpos, c, sep, rng):
  # on a principal axis of the (randomly rotated) ellipsoid: the centre line is the normal
  return _sphere_on_ellipsoid(mjm, qpos, c, sep, rng, ("sph", "ell"), [1.0, 0, 0])


def sphere_ellipsoid_generic(mjm, qpos, c, sep, rng):
  # a generic surface point: the normal is 18 degrees off the line between the centres
  return _sphere_on_ellipsoid(mjm, qpos, c, sep, rng, ("gsph", "gell"), [0.5, -0.3, 0.8])


def cylinder_box(mjm, qpos, c, sep, rng):
  off = np.array([0.02, -0.015, 0.0])
  free_body_qpos(mjm, qpos, "cylbase", c, yaw(0.3))
  top = c[2] + 0.05
  free_body_qpos(mjm, qpos, "cyl", c + off + [0, 0, 0.05 + 0.04 + sep], yaw(1.1))
  # geom1 is the cylinder (CYLINDER < BOX): the normal points down into the box
  return "cyl", "cylbase", np.array([0, 0, -1.0]), np.array([c[0] + off[0], c[1] + off[1], top + sep / 2]), 0.03


def _cube_on(mjm, qpos, c, sep, names, base_half_z, base_yaw, cube_yaw, off):
  low, high = names
  off = np.array([off[0], off[1], 0.0])
  free_body_qpos(mjm, qpos, low, c, yaw(base_yaw))
  top = c[2] + base_half_z
  free_body_qpos(mjm, qpos, high, c + off + [0, 0, base_half_z + 0.05 + sep], yaw(cube_yaw))
  return low, high, np.array([0, 0, 1.0]), np.array([c[0] + off[0], c[1] + off[1], top + sep / 2]), 0.05 * np.sqrt(2)


def box_meshbox(mjm, qpos, c, sep, rng):
  # geom1 is the box primitive (BOX < MESH): the normal points up into the mesh cube
  return _cube_on(mjm, qpos, c, sep, ("mbase", "mcube"), 0.05, -0.2, 0.5, (0.015, 0.01))


def meshbox_meshbox(mjm, qpos, c, sep, rng):
  return _cube_on(mjm, qpos, c, sep, ("mlow", "mhigh"), 0.05, 0.0, np.pi / 6, (0.02, -0.01))


def margin_spheres(mjm, qpos, c, sep, rng):
  u = unit([-0.3, 0.8, 0.5])
  r = 0.04
  free_body_qpos(mjm, qpos, "mg_a", c, random_quat(rng))
  free_body_qpos(mjm, qpos, "mg_b", c + u * (2 * r + sep), random_quat(rng))
  return "mg_a", "mg_b", u, c + u * (r + sep / 2), None


def margin_box_meshbox(mjm, qpos, c, sep, rng):
  return _cube_on(mjm, qpos, c, sep, ("mgc_low", "mgc_high"), 0.05, 0.4, -0.7, (-0.01, 0.02))


# name: (builder, slot centre, penetration depth in world 0, has a margin > GAP)
CASES = {
  "ellipsoid-ellipsoid": (spheres_oblique, (-1.2, 0.0, 0.0), 0.01, False),
  "ellipsoid-ellipsoid-axis": (spheres_on_axis, (-1.2, 0.6, 0.0), 0.004, False),
  "sphere-ellipsoid": (sphere_ellipsoid, (-0.6, 0.0, 0.0), 0.008, False),
  "cylinder-box": (cylinder_box, (0.0, 0.0, 0.0), 0.006, False),
  "box-meshbox": (box_meshbox, (0.6, 0.0, 0.0), 0.007, False),
  "meshbox-meshbox": (meshbox_meshbox, (1.2, 0.0, 0.0), 0.005, False),
  "margin-ellipsoid": (margin_spheres, (-0.6, 0.6, 0.0), 0.003, True),
  "margin-box-meshbox": (margin_box_meshbox, (0.0, 0.6, 0.0), 0.004, True),
  "sphere-ellipsoid-generic": (sphere_ellipsoid_generic, (0.6, 0.6, 0.0), 0.008, False),
}
EXACT = [k for k in CASES if k != "sphere-ellipsoid-generic"]


@pytest.fixture(scope="module")
def scene():
  sim = load(XML, nworld=2)
  mjm = sim.mjm
  qpos = [mjm.qpos0.copy(), mjm.qpos0.copy()]
  expected = [{}, {}]
  for name, (build, slot, depth, has_margin) in CASES.items():
    for world, sep in ((0, -depth), (1, GAP)):
      rng = np.random.default_rng(zlib.crc32(name.encode()))
      g1, g2, normal, pos, patch = build(mjm, qpos[world], np.array(slot, dtype=np.float64), sep, rng)
      if world == 1 and not has_margin:
        continue
      expected[world][name] = dict(g1=geom_id(mjm, g1), g2=geom_id(mjm, g2), dist=sep, normal=normal, pos=pos, patch=patch)
  set_qpos(sim, np.stack(qpos))
  return sim, expected


@pytest.fixture(scope="module", params=["refined", "exact"])
def result(request, scene):
  sim, expected = scene
  # one (the deepest) contact per pair: these tests check MPR itself; test_multicontact.py the rest
  sf.install(sim.mjm, sim.m, sf.Options(support_mode=request.param, multi_contact=False))
  try:
    sf.collision(sim.m, sim.d)
    got = [contacts(sim.d, 0), contacts(sim.d, 1)]
  finally:
    sf.uninstall(sim.m)
  return request.param, got, expected


def _check_contact(mode, got, e, case, world):
  c = got[world]
  sel = [i for i in range(c.n) if tuple(c.geom[i]) == (e["g1"], e["g2"])]
  rev = [i for i in range(c.n) if tuple(c.geom[i]) == (e["g2"], e["g1"])]
  where = f"{case} ({mode}, world {world})"
  assert not rev, f"{where}: contact written with the geoms swapped"
  assert len(sel) == 1, f"{where}: {len(sel)} contacts, expected one (MPR gives the deepest only)"
  i = sel[0]
  dist, normal, pos = float(c.dist[i]), c.normal[i], c.pos[i]
  assert dist == pytest.approx(e["dist"], rel=1e-4), f"{where}: dist {dist:.8f}, expected {e['dist']:.8f}"
  ang = angle_deg(normal, e["normal"])
  assert ang < 0.5, f"{where}: normal {normal} is {ang:.3f} deg off {e['normal']}"
  assert np.linalg.norm(c.frame[i] @ c.frame[i].T - np.eye(3)) < 1e-4, f"{where}: contact frame is not orthonormal"
  # positions: MPR's midpoint interpolates the portal's support points barycentrically, with a
  # small weight on the centres (libccd does the same), so it sits up to ~10 % of the depth off
  # the analytic midpoint; "a few mm" of slack covers that and still catches a wrong margin shift
  if e["patch"] is None:
    err = np.linalg.norm(pos - e["pos"])
    assert err < 1.5e-3, f"{where}: contact position {pos} is {err * 1e3:.3f} mm off {e['pos']}"
  else:
    # face contact: the midpoint plane is known, the point can be anywhere in the contact patch
    assert abs(pos[2] - e["pos"][2]) < 1.5e-3, f"{where}: contact z {pos[2]:.6f}, expected {e['pos'][2]:.6f}"
    lateral = np.linalg.norm(pos[:2] - e["pos"][:2])
    assert lateral <= e["patch"] + 1e-4, f"{where}: contact {lateral * 1e3:.1f} mm from the patch centre"


def test_only_intended_pairs_touch(result):
  """Every contact belongs to a case (the slots do not interact), one per pair."""
  _, got, expected = result
  for world in (0, 1):
    allowed = {(e["g1"], e["g2"]) for e in expected[world].values()}
    pairs = [tuple(int(x) for x in g) for g in got[world].geom]
    assert set(pairs) <= allowed, f"world {world}: unexpected contacts {set(pairs) - allowed}"
    assert len(pairs) == len(set(pairs)) == len(allowed), f"world {world}: contacts {pairs}, expected {allowed}"


@pytest.mark.parametrize("case", EXACT)
def test_penetrating_pair(result, case):
  mode, got, expected = result
  _check_contact(mode, got, expected[0][case], case, 0)


@pytest.mark.parametrize("case", [k for k in CASES if CASES[k][3]])
def test_separated_pair_within_margin(result, case):
  mode, got, expected = result
  _check_contact(mode, got, expected[1][case], case, 1)


def test_separated_pairs_have_no_contact(result):
  mode, got, expected = result
  c = got[1]
  margin_pairs = {(e["g1"], e["g2"]) for e in expected[1].values()}
  other = [tuple(int(x) for x in g) for g in c.geom if tuple(int(x) for x in g) not in margin_pairs]
  assert not other, f"({mode}) pairs {GAP} m apart gave contacts {other}"
  assert np.all(c.dist > 0), f"({mode}) separated pairs have non-positive dist {c.dist}"


def test_sphere_ellipsoid_generic_point(result):
  mode, got, expected = result
  _check_contact(mode, got, expected[0]["sphere-ellipsoid-generic"], "sphere-ellipsoid-generic", 0)


PLATE = " ".join(f"{x} {y} {z}" for x in (-0.5, 0.5) for y in (-0.5, 0.5) for z in (-0.0005, 0.0005))
PLATES_XML = f"""
<mujoco model="crossing_plates">
  <asset><mesh name="plate" vertex="{PLATE}"/></asset>
  <worldbody>
    <body><freejoint/><geom type="mesh" mesh="plate"/></body>
    <body><freejoint/><geom type="mesh" mesh="plate"/></body>
  </worldbody>
</mujoco>
"""


@pytest.mark.parametrize("tilt", [0.005, 0.01, 0.03])
def test_thin_plates_crossing_take_the_shallow_axis(tilt):
  """Two 1 mm plates 1 m wide, offset sideways and crossing at a small angle: MPR's ray from the
  centres leaves through the plates' ends (0.7 m deep); the axis check finds MuJoCo C's depth
  across the thickness."""
  mjm = mujoco.MjModel.from_xml_string(PLATES_XML)
  qpos = np.array([0, 0, 0, 1, 0, 0, 0, 0.3, 0.1, 0.001 - 1e-5, np.cos(tilt / 2), np.sin(tilt / 2), 0, 0])
  mjd = mujoco.MjData(mjm)
  mjd.qpos[:] = qpos
  mujoco.mj_forward(mjm, mjd)
  want = min(c.dist for c in mjd.contact[: mjd.ncon])
  sim = load(None, mjm=mjm, qpos=qpos, naconmax=64)
  sf.install(sim.mjm, sim.m)
  sf.collision(sim.m, sim.d)
  got = contacts(sim.d, 0)
  assert got.n >= 1
  assert abs(got.dist.min() - want) < 2e-5, (got.dist.min(), want)
  for normal in got.normal:
    assert angle_deg(normal, mjd.contact[0].frame[:3]) < 2.0 * np.degrees(tilt) + 0.1
