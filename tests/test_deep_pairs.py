"""Deep pairs (issue #20, item 2): MPR's deep answers checked along the shapes' faces
(deep_pairs.py).

MPR on a deep polytope pair settles on a face of A - B that the origin projects into, not always
the nearest: with default options the answer must be within 5 degrees of MuJoCo C's normal or no
worse a separating direction (exact overlap of the two hulls along it, float64), and never worse
than the best of the hulls' face normals. Only deep answers go to the check: a resting pair does
not. The reduced real-model case lives in tests/data/repro (see its README).
"""

import os

import mujoco
import numpy as np
import pytest

import mjx_supportfield as sf
from conftest import ROOT
from conftest import angle_deg
from conftest import contacts
from conftest import load
from conftest import random_quat
from conftest import set_qpos
from mjx_supportfield.tools import exact

REPRO = os.path.join(ROOT, "tests", "data", "repro")
NORMAL_FAR_DEG = 5.0
OVERLAP_TOL = 1e-6  # [m] float32 poses and normals: overlaps closer than this tie


def overlap(mjm, g1, g2, xpos, xmat, normal) -> float:
  return exact.overlap_along(mjm, g1, g2, xpos, xmat.reshape(-1, 3, 3), np.asarray(normal, np.float64))


def deepest(c):
  """Geoms and normal of the deepest of some contacts (one pair)."""
  k = int(np.argmin(c.dist))
  return tuple(int(x) for x in c.geom[k]), c.normal[k].astype(np.float64)


@pytest.mark.parametrize("name", ["mpr_dodeca_tetra.xml", "mpr_dodeca_tetra_edges.xml"])
def test_mpr_dodeca_tetra_normal(name):
  """A dodecahedron deep in a tetrahedron: MPR stopped on one of the dodecahedron's faces, 58.7
  degrees off MuJoCo C's normal and 2.95 mm deep along it, where C's normal overlaps 2.11 mm;
  in the other pose 31 degrees off, 6.47 mm against 5.85 along C's, an edge-edge direction that
  no face normal of either hull matches."""
  mjm = mujoco.MjModel.from_xml_path(os.path.join(REPRO, name))
  sim = load(None, mjm=mjm)
  collider = sf.install(mjm, sim.m)
  sf.collision(sim.m, sim.d)
  c = contacts(sim.d, 0)
  assert c.n > 0
  geoms, normal = deepest(c)
  ref = sim.mjd.contact[int(np.argmin(sim.mjd.contact.dist[: sim.mjd.ncon]))]
  ref_normal = np.array(ref.frame[:3]) * (1 if (ref.geom1, ref.geom2) == geoms else -1)
  xpos, xmat = exact.geom_poses(mjm, sim.mjd.qpos)
  mine = overlap(mjm, *geoms, xpos, xmat, normal)
  theirs = overlap(mjm, *geoms, xpos, xmat, ref_normal)
  angle = angle_deg(normal, ref_normal)
  assert angle <= NORMAL_FAR_DEG or mine <= theirs + OVERLAP_TOL, (
    f"normal {angle:.1f} deg off MuJoCo C's with overlap {mine * 1e3:.3f} mm along it, C's {theirs * 1e3:.3f} mm")
  # every contact of the pair (the multi-contact pass's too) carries the corrected normal
  assert max(angle_deg(n, normal) for n in c.normal) < 1e-3
  assert collider.stats(sim.d)["deep_pairs"] == 1


RESTING = """
<mujoco>
  <asset><mesh name="tetra" vertex="0 0 0  .04 0 0  0 .04 0  0 0 .04"/></asset>
  <worldbody>
    <geom name="table" type="box" size=".2 .2 .02" pos="0 0 -.02"/>
    <body pos="0 0 -.0002"><freejoint/><geom name="tetra" type="mesh" mesh="tetra"/></body>
  </worldbody>
</mujoco>
"""


def test_resting_pair_is_not_checked():
  """A tetrahedron resting face down on a box, 0.2 mm sunk: its answer is not queued for the
  check, and its contacts are the face's corners along the box's normal."""
  sim = load(RESTING)
  collider = sf.install(sim.mjm, sim.m)
  sf.collision(sim.m, sim.d)
  stats = collider.stats(sim.d)
  assert stats["deep_pairs"] == 0 and stats["deep_pairs_unchecked"] == 0
  c = contacts(sim.d, 0)
  assert c.n >= 3
  assert max(angle_deg(np.abs(n), (0, 0, 1)) for n in c.normal) < 1e-3


# --- random deep hull pairs -----------------------------------------------------------------------

NEXAMPLE = 4  # models: hull-hull and hull-box in turn
NPOSE = 8  # deep poses of B per model, one per world


def _hull(rng) -> np.ndarray:
  """8 to 30 points on and inside a random ellipsoid with semi-axes 1 to 5 cm."""
  p = rng.normal(size=(int(rng.integers(8, 31)), 3))
  p /= np.linalg.norm(p, axis=1, keepdims=True)
  return p * rng.uniform(0.5, 1.0, (len(p), 1)) ** (1 / 3) * rng.uniform(0.01, 0.05, 3)


def _vertices(points) -> str:
  return " ".join(f"{x:.7g}" for x in np.ravel(points))


def _example(k: int):
  """Model (static hull A, free shape B: a hull or a box) and NPOSE qpos rows, each with B
  turned at random and moved along a random direction until the shapes' extents along it
  overlap by 15 to 40 %."""
  rng = np.random.default_rng([20, k])
  while True:
    if k % 2 == 0:
      b_asset, b_geom = f'<mesh name="B" vertex="{_vertices(_hull(rng))}"/>', '<geom name="B" type="mesh" mesh="B"/>'
    else:
      size = rng.uniform(0.01, 0.04, 3)
      b_asset, b_geom = "", f'<geom name="B" type="box" size="{_vertices(size)}"/>'
    xml = f"""<mujoco><option gravity="0 0 0"/><asset><mesh name="A" vertex="{_vertices(_hull(rng))}"/>{b_asset}</asset>
      <worldbody><geom name="A" type="mesh" mesh="A"/><body name="B"><freejoint/>{b_geom}</body></worldbody></mujoco>"""
    try:
      mjm = mujoco.MjModel.from_xml_string(xml)
      break
    except ValueError:  # a degenerate random hull
      continue
  qpos = np.tile(mjm.qpos0, (NPOSE, 1))
  mjd = mujoco.MjData(mjm)
  for w in range(NPOSE):
    u = rng.normal(size=3)
    u /= np.linalg.norm(u)
    quat = random_quat(rng)
    mjd.qpos[:] = 0
    mjd.qpos[3:7] = quat
    mujoco.mj_kinematics(mjm, mjd)
    xpos, xmat = mjd.geom_xpos, mjd.geom_xmat.reshape(-1, 3, 3)
    reach = exact.support(mjm, 0, xpos[0], xmat[0], u) + exact.support(mjm, 1, xpos[1], xmat[1], -u)
    qpos[w, :3] = u * reach * (1 - rng.uniform(0.15, 0.4))
    qpos[w, 3:7] = quat
  return mjm, qpos


def _face_normals(mjm, g, xmat) -> np.ndarray:
  """World outward unit normals of geom g's hull faces (a box's six)."""
  if mjm.geom_type[g] == mujoco.mjtGeom.mjGEOM_BOX:
    return np.concatenate([xmat.T, -xmat.T])
  return exact.mesh_hull(mjm, int(mjm.geom_dataid[g])).normal @ xmat.T


@pytest.mark.parametrize("k", range(NEXAMPLE))
def test_random_deep_pairs_no_worse_than_faces(k):
  """MPR's normal, checked, is never a worse separating direction than the best face normal of
  the two hulls (A's outward normals, B's inward ones: the directions from A to B along which
  A - B has a face of that kind)."""
  mjm, qpos = _example(k)
  sim = load(None, mjm=mjm, nworld=NPOSE, qpos=qpos)
  sf.install(mjm, sim.m)
  sf.collision(sim.m, sim.d)
  worse, ndeep = [], 0
  mjd = mujoco.MjData(mjm)
  for w in range(NPOSE):
    c = contacts(sim.d, w)
    xpos, xmat = exact.geom_poses(mjm, qpos[w], mjd)
    if c.n == 0:  # overlapping extents along a direction need not overlap: MuJoCo C says whether
      assert mujoco.mj_geomDistance(mjm, mjd, 0, 1, 1.0, None) > -1e-5, f"world {w}: overlap but no contact"
      continue
    ndeep += 1
    geoms, normal = deepest(c)
    g1, g2 = geoms
    faces = np.concatenate([_face_normals(mjm, g1, xmat[g1]), -_face_normals(mjm, g2, xmat[g2])])
    best = min(overlap(mjm, g1, g2, xpos, xmat, n) for n in faces)
    mine = overlap(mjm, g1, g2, xpos, xmat, normal)
    size = min(mjm.geom_rbound)
    if mine > best + 1e-4 * size + OVERLAP_TOL:
      worse.append(f"world {w}: overlap {mine * 1e3:.4f} mm along the normal, {best * 1e3:.4f} mm along a face normal")
  assert ndeep >= 2
  assert not worse, "\n".join(worse)


def test_deep_pairs_beyond_the_queue_keep_mpr_answer(monkeypatch):
  """With no rows of the queue for any world, every deep answer is counted and keeps MPR's
  answer: every overlapping world still gets its contacts."""
  from mjx_supportfield.stages import deep_pairs

  monkeypatch.setattr(deep_pairs, "DEEP_PAIRS_PER_WORLD", 0)
  mjm, qpos = _example(0)
  sim = load(None, mjm=mjm, nworld=NPOSE, qpos=qpos)
  collider = sf.install(mjm, sim.m)
  sf.collision(sim.m, sim.d)
  stats = collider.stats(sim.d)
  touching = [w for w in range(NPOSE) if contacts(sim.d, w).n]
  assert stats["deep_pairs"] >= 2 and stats["deep_pairs_unchecked"] == stats["deep_pairs"]
  assert "beyond their world's rows of the check's queue" in str(stats)
  mjd = mujoco.MjData(mjm)
  for w in set(range(NPOSE)) - set(touching):
    mjd.qpos[:] = qpos[w]
    mujoco.mj_kinematics(mjm, mjd)
    assert mujoco.mj_geomDistance(mjm, mjd, 0, 1, 1.0, None) > -1e-5, f"world {w}: overlap but no contact"


def test_deep_hull_box_edge_edge():
  """A hull deep in a box (random example 117, pose 4) whose penetration direction is an
  edge-edge one 64 degrees from the best face normal, out of reach of the walk from the faces:
  every edge pair of the small hull and the box is tried, and the answer is as good as EPA's."""
  mjm, qpos = _example(117)
  normals = {}
  for name, options in (("mpr", sf.Options()), ("gjk", sf.Options(narrowphase="gjk"))):
    sim = load(None, mjm=mjm, nworld=1, qpos=qpos[4])
    sf.install(mjm, sim.m, options)
    sf.collision(sim.m, sim.d)
    normals[name] = deepest(contacts(sim.d, 0))
  (g1, g2), normal = normals["mpr"]
  assert normals["gjk"][0] == (g1, g2)
  xpos, xmat = exact.geom_poses(mjm, qpos[4])
  mine, epa = (overlap(mjm, g1, g2, xpos, xmat, n) for n in (normal, normals["gjk"][1]))
  assert mine <= epa + OVERLAP_TOL, f"overlap {mine * 1e3:.3f} mm along the normal, EPA's {epa * 1e3:.3f} mm"


# --- persistent deep pairs: the check's verdict reused, rechecked every few calls -----------------

OCTAHEDRA = """
<mujoco>
  <option gravity="0 0 0"/>
  <asset>
    <mesh name="big" vertex=".06 0 0  -.06 0 0  0 .06 0  0 -.06 0  0 0 .06  0 0 -.06"/>
    <mesh name="small" vertex=".01 0 0  -.01 0 0  0 .01 0  0 -.01 0  0 0 .01  0 0 -.01"/>
  </asset>
  <worldbody>
    <geom name="big" type="mesh" mesh="big"/>
    <body name="small"><freejoint/><geom name="small" type="mesh" mesh="small"/></body>
  </worldbody>
</mujoco>
"""
SUNK = 0.006  # the small octahedron's depth under the big one's (1, 1, 1) face
SLIDE_Z = (0.004, 0.002, 0.0, -0.001, -0.002, -0.003)  # its centre's z, kept at that depth


def _slide(calls: int):
  """(normal from the big octahedron to the small one, depth) of the deepest contact after each
  call: the small octahedron SUNK under the big one's (1, 1, 1) face, slid along it over the
  edge with the (1, 1, -1) face (z from + to -), then held ``calls`` calls at z = -3 mm, where
  the (1, 1, -1) face is the nearer way out (2.54 mm against 6). Its local axes are no face
  normals, so MPR's own axis check does not find the other face."""
  sim = load(OCTAHEDRA)
  collider = sf.install(sim.mjm, sim.m)
  qpos = sim.mjm.qpos0.copy()
  along = 0.07 - SUNK * np.sqrt(3)  # x + y + z of the centre: the depth under the (1, 1, 1) face
  out, reused = [], 0
  for z in SLIDE_Z + (SLIDE_Z[-1],) * calls:
    qpos[:3] = ((along - z) / 2, (along - z) / 2, z)
    set_qpos(sim, qpos)
    sf.collision(sim.m, sim.d)
    c = contacts(sim.d, 0)
    row = int(np.argmin(c.dist))
    sign = 1 if tuple(c.geom[row]) == (0, 1) else -1
    out.append((sign * c.normal[row], -float(c.dist[row])))
    reused += collider.stats(sim.d)["deep_pairs_reused"]
  return out, reused


def test_deep_pair_rechecked_when_nearest_face_changes(monkeypatch):
  """The small octahedron slides under the big one's face until another face is the nearer way
  out. MPR warm-started from the first face's normal stays on it (its ray still leaves through
  that face), so it agrees with the check's last verdict and the check is skipped; the pair is
  rechecked within DEEP_RECHECK_CALLS calls and then follows the nearer face. With the recheck
  pushed out of reach the answer stays on the first face, 6 mm deep instead of 2.54."""
  from mjx_supportfield.stages import narrowphase

  first, second = np.array((1, 1, 1)) / np.sqrt(3), np.array((1, 1, -1)) / np.sqrt(3)
  period = narrowphase.DEEP_RECHECK_CALLS
  normals, reused = _slide(period)
  assert angle_deg(normals[0][0], first) < 1.0
  assert reused > 0  # the verdict was kept on some calls
  assert angle_deg(normals[-1][0], second) < 1.0, f"normal {normals[-1][0]} {period} calls after the slide"
  assert abs(normals[-1][1] - (SUNK + 2 * SLIDE_Z[-1] / np.sqrt(3))) < 1e-4
  monkeypatch.setattr(narrowphase, "DEEP_RECHECK_CALLS", 1 << 20)
  stuck, _ = _slide(period)
  assert angle_deg(stuck[-1][0], first) < 1.0, "without the recheck MPR should stay on the first face"


@pytest.mark.parametrize("k", range(4))
@pytest.mark.parametrize("lanes", [3, 16])
def test_lanes_answer_as_one_thread(k, lanes):
  """A pair's scans dealt to several lanes (as on a GPU) give the contacts of one thread scanning
  every candidate in order, bit for bit: the lanes merge to the earliest candidate of least
  overlap (a box's parallel faces and edges tie exactly)."""
  mjm, qpos = _example(k)
  sim = load(None, mjm=mjm, nworld=NPOSE, qpos=qpos)
  collider = sf.install(mjm, sim.m, sf.Options(warm_start=False))
  state = collider.state(sim.m, sim.d)
  rows = {}
  for nlane in (1, lanes):
    state.deep.max_lanes = nlane
    sf.collision(sim.m, sim.d)
    assert collider.stats(sim.d)["deep_pairs"] >= 2
    n = int(sim.d.nacon.numpy()[0])
    rows[nlane] = [getattr(sim.d.contact, f).numpy()[:n].copy() for f in ("dist", "pos", "frame", "geom", "worldid")]
  for one, laned in zip(rows[1], rows[lanes]):
    np.testing.assert_array_equal(one, laned)


def test_captured_check_runs_only_when_queued():
  """In a graph the check is gated on its queue (wp.capture_if): replayed with deep answers
  queued, and then with none, the graph gives the contacts of plain calls, bit for bit."""
  import warp as wp

  mjm, qpos = _example(0)
  sim = load(None, mjm=mjm, nworld=NPOSE, qpos=qpos)
  ref = load(None, mjm=mjm, nworld=NPOSE, qpos=qpos)
  collider = sf.install(mjm, sim.m, sf.Options(warm_start=False))
  sf.collision(sim.m, sim.d)  # loads every kernel and makes the per-Data state before capturing
  sf.collision(sim.m, ref.d)
  with wp.ScopedCapture() as capture:
    sf.collision(sim.m, sim.d)
  apart = qpos.copy()
  apart[:, 2] += 1.0  # B lifted clear of A in every world: nothing to check
  for poses, deep in ((qpos, True), (apart, False)):
    for s in (sim, ref):
      set_qpos(s, poses)
    wp.capture_launch(capture.graph)
    sf.collision(sim.m, ref.d)
    assert (collider.stats(ref.d)["deep_pairs"] > 0) == deep
    n = int(ref.d.nacon.numpy()[0])
    assert int(sim.d.nacon.numpy()[0]) == n
    for field in ("dist", "pos", "frame", "geom", "worldid"):
      np.testing.assert_array_equal(getattr(sim.d.contact, field).numpy()[:n], getattr(ref.d.contact, field).numpy()[:n])
