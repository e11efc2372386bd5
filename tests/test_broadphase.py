"""Broad phase: the plugin's pair list against a brute-force AABB set and MuJoCo C's contacts."""

import mujoco
import mujoco_warp as mjw
import numpy as np
import pytest
from mujoco_warp._src.types import GeomType
from mujoco_warp._src.types import OverflowType

import mjx_supportfield as sf
from mjx_supportfield.stages import broadphase
from mjx_supportfield.stages import routing as nph
from conftest import bitwise_repeatable
from conftest import contacts
from conftest import load
from conftest import random_quat
from conftest import set_qpos
from conftest import sorted_rows
from conftest import world_contact_fields

NWORLD = 2


def plugin_pairs(m, d):
  """{world: list of (g1, g2) as written} from the plugin's per-Data state."""
  st = sf.get_collider(m).state(m, d).broad
  n = int(st.npair.numpy()[0])
  assert 0 <= n <= st.capacity
  pair = st.pair.numpy()[:n].reshape(-1, 2)
  wid = st.pair_worldid.numpy()[:n]
  out = {w: [] for w in range(d.nworld)}
  for (g1, g2), w in zip(pair, wid):
    assert 0 <= w < d.nworld
    out[int(w)].append((int(g1), int(g2)))
  return out


def world_aabbs(sim, world, slack=1e-6):
  """(lo, hi) (ngeom, 3) in float64 from geom_xpos / geom_xmat / m.geom_aabb, inflated by
  margin + gap (+ slack against float32 rounding); None for planes."""
  xpos = sim.d.geom_xpos.numpy()[world].astype(np.float64)
  xmat = sim.d.geom_xmat.numpy()[world].reshape(-1, 3, 3).astype(np.float64)
  aabb = sim.m.geom_aabb.numpy()[0].astype(np.float64)  # (ngeom, 2, 3): center, half size
  inflate = sim.mjm.geom_margin + sim.mjm.geom_gap + slack
  center = xpos + np.einsum("gij,gj->gi", xmat, aabb[:, 0])
  half = np.einsum("gij,gj->gi", np.abs(xmat), aabb[:, 1]) + inflate[:, None]
  return center - half, center + half, xpos, xmat, inflate


def brute_force_pairs(sim, world):
  """Unordered pairs whose world AABBs overlap (planes as half-spaces) and that MuJoCo's static
  filters keep (m.nxn_pairid[:, 0] != -2)."""
  mjm = sim.mjm
  lo, hi, xpos, xmat, inflate = world_aabbs(sim, world)
  geom_pair = sim.m.nxn_geom_pair.numpy().reshape(-1, 2)
  pairid = sim.m.nxn_pairid.numpy().reshape(-1, 2)
  out = set()
  for (g1, g2), pid in zip(geom_pair, pairid):
    if pid[0] == -2:
      continue
    t1, t2 = mjm.geom_type[g1], mjm.geom_type[g2]
    if t1 == GeomType.PLANE and t2 == GeomType.PLANE:
      continue
    if t1 == GeomType.PLANE or t2 == GeomType.PLANE:
      p, o = (g1, g2) if t1 == GeomType.PLANE else (g2, g1)
      normal = xmat[p][:, 2]
      corners = np.array([[x, y, z] for x in (lo[o, 0], hi[o, 0]) for y in (lo[o, 1], hi[o, 1])
                          for z in (lo[o, 2], hi[o, 2])])
      ok = np.min((corners - xpos[p]) @ normal) <= inflate[p]
    else:
      ok = np.all(lo[g1] <= hi[g2]) and np.all(lo[g2] <= hi[g1])
    if ok:
      out.add((int(min(g1, g2)), int(max(g1, g2))))
  return out


def mjc_pairs(mjm, qpos):
  """Unordered geom pairs MuJoCo C reports contacts for at qpos."""
  mjd = mujoco.MjData(mjm)
  mjd.qpos[:] = qpos
  mujoco.mj_kinematics(mjm, mjd)
  mujoco.mj_collision(mjm, mjd)
  return {(min(c.geom1, c.geom2), max(c.geom1, c.geom2)) for c in mjd.contact[: mjd.ncon]}


def perturbed_qpos(mjm, rng, scale_pos, max_angle):
  """qpos0 with every free joint moved by up to scale_pos and rotated by up to max_angle."""
  qpos = mjm.qpos0.copy()
  for j in range(mjm.njnt):
    if mjm.jnt_type[j] != mujoco.mjtJoint.mjJNT_FREE:
      continue
    adr = mjm.jnt_qposadr[j]
    qpos[adr : adr + 3] += rng.uniform(-scale_pos, scale_pos, 3)
    q = np.empty(4)
    mujoco.mju_mulQuat(q, random_quat(rng, max_angle), qpos[adr + 3 : adr + 7])
    qpos[adr + 3 : adr + 7] = q
  return qpos


def mirrored_qpos(mjm, qpos):
  """Free bodies mirrored through x = 0 (reverses their order along the sweep axis)."""
  qpos = qpos.copy()
  for j in range(mjm.njnt):
    if mjm.jnt_type[j] == mujoco.mjtJoint.mjJNT_FREE:
      adr = mjm.jnt_qposadr[j]
      qpos[adr] = -qpos[adr]
  return qpos


def check_pairs(sim, qpos_worlds, label):
  """Runs the plugin on qpos_worlds and checks every world's pair list."""
  set_qpos(sim, qpos_worlds)
  sf.collision(sim.m, sim.d)
  got = plugin_pairs(sim.m, sim.d)
  gtype = sim.mjm.geom_type
  nmjc = 0
  for w in range(sim.d.nworld):
    pairs = got[w]
    unordered = [(min(p), max(p)) for p in pairs]
    assert len(set(unordered)) == len(unordered), f"{label} world {w}: duplicate pairs {sorted(unordered)}"
    for g1, g2 in pairs:
      assert g1 != g2
      assert gtype[g1] <= gtype[g2], f"{label} world {w}: pair ({g1}, {g2}) is not ordered by geom type"
    brute = brute_force_pairs(sim, w)
    extra = set(unordered) - brute
    assert not extra, f"{label} world {w}: pairs without overlapping AABBs or filtered out: {sorted(extra)}"
    ref = mjc_pairs(sim.mjm, qpos_worlds[w])
    nmjc += len(ref)
    missing = ref - set(unordered)
    assert not missing, f"{label} world {w}: MuJoCo C has contacts for {sorted(missing)}, the broad phase missed them"
    stats = sf.get_collider(sim.m).stats(sim.d)
    assert stats["pairs_per_world"][w] == len(pairs)
    assert stats["dropped_pairs_per_world"][w] == 0
  assert nmjc >= 3, f"{label}: too few MuJoCo C contacts ({nmjc}) for a meaningful check"
  assert not np.any(sim.d.overflow.numpy() & int(OverflowType.BROADPHASE))


@pytest.mark.parametrize("broadphase,sap_axis", [("sap", 0), ("sap", 2), ("nxn", 0)])
@pytest.mark.parametrize("scene", ["primitives_plane", "convex_pile"])
def test_pairs_against_brute_force(scene, broadphase, sap_axis):
  rng = np.random.default_rng(1234 + sap_axis)
  sim = load(scene, nworld=NWORLD)
  sf.install(sim.mjm, sim.m, sf.Options(broadphase=broadphase, sap_axis=sap_axis))
  assert sf.get_collider(sim.m).broad.nxn == (broadphase == "nxn")
  mjm = sim.mjm
  scale = 0.01 if scene == "convex_pile" else 0.02

  q0 = np.stack([perturbed_qpos(mjm, rng, scale, 0.3) for _ in range(NWORLD)])
  check_pairs(sim, q0, "first call")
  # warm start: same poses again, then small motions, then a mirror that reverses the order
  check_pairs(sim, q0, "unchanged")
  q1 = np.stack([perturbed_qpos(mjm, rng, 0.5 * scale, 0.1) for _ in range(NWORLD)])
  q1 = 0.5 * (q0 + q1)
  for w in range(NWORLD):
    for j in range(mjm.njnt):
      adr = mjm.jnt_qposadr[j]
      q1[w, adr + 3 : adr + 7] /= np.linalg.norm(q1[w, adr + 3 : adr + 7])
  check_pairs(sim, q1, "small motion")
  q2 = np.stack([mirrored_qpos(mjm, q1[w]) for w in range(NWORLD)])
  check_pairs(sim, q2, "mirrored")
  # the two worlds swap poses: each world's saved order is stale
  check_pairs(sim, q2[::-1].copy(), "worlds swapped")


def test_auto_broadphase_follows_the_pair_count(monkeypatch):
  """"auto" takes nxn up to NXN_MAX_PAIRS statically kept pairs (times the share of moving
  geoms: nearly all here) and sweep-and-prune beyond."""
  sim = load("primitives_plane", nworld=1)
  npair = len(sim.m.nxn_geom_pair_filtered.numpy())
  assert sf.install(sim.mjm, sim.m).broad.nxn
  sf.uninstall(sim.m)
  monkeypatch.setattr(broadphase, "NXN_MAX_PAIRS", npair // 2)
  assert not sf.install(sim.mjm, sim.m).broad.nxn
  sf.uninstall(sim.m)


def test_auto_broadphase_counts_static_geoms_apart(monkeypatch):
  """Static geoms (a terrain's stair boxes) raise "auto"'s nxn limit by the ratio of all the
  paired geoms to the moving ones: the sweep walks the static ones every step, nxn only their
  pairs with moving geoms."""
  boxes = "".join(f'<geom type="box" size=".1 .1 .1" pos="{0.3 * i} 0 0"/>' for i in range(40))
  mjm = mujoco.MjModel.from_xml_string(
    f'<mujoco><worldbody>{boxes}<body pos="0 0 1"><freejoint/><geom size=".1"/></body>'
    '<body pos="1 0 1"><freejoint/><geom size=".1"/></body></worldbody></mujoco>')
  pairs = np.asarray(mjw.put_model(mjm).nxn_geom_pair_filtered.numpy()).reshape(-1, 2)
  assert len(pairs) == 81  # each sphere with each box, and the two spheres
  monkeypatch.setattr(broadphase, "NXN_MAX_PAIRS", 10)
  assert broadphase.nxn_pair_limit(mjm, pairs) == 10 * 42 // 2
  m = mjw.put_model(mjm)
  assert sf.install(mjm, m).broad.nxn
  sf.uninstall(m)
  bodies = "".join(f'<body pos="{0.3 * i} 0 0"><freejoint/><geom type="box" size=".1 .1 .1"/></body>' for i in range(14))
  free = mujoco.MjModel.from_xml_string(f"<mujoco><worldbody>{bodies}</worldbody></mujoco>")
  pairs = np.asarray(mjw.put_model(free).nxn_geom_pair_filtered.numpy()).reshape(-1, 2)
  assert broadphase.nxn_pair_limit(free, pairs) == 10  # every geom moves: the limit as it is


@pytest.fixture(scope="module")
def overflow_scene():
  sim = load("primitives_plane", nworld=NWORLD)
  return sim


@pytest.mark.parametrize("broadphase", ["sap", "nxn"])
def test_broadphase_overflow(overflow_scene, broadphase):
  sim = overflow_scene
  rng = np.random.default_rng(7)
  q = np.stack([perturbed_qpos(sim.mjm, rng, 0.01, 0.1) for _ in range(NWORLD)])
  set_qpos(sim, q)
  m, d = sim.m, sim.d

  # reference pair count with the default budget
  sf.install(sim.mjm, m, sf.Options(broadphase=broadphase))
  d.overflow.zero_()
  sf.collision(m, d)
  full = [len(v) for v in plugin_pairs(m, d).values()]
  assert min(full) > 2, f"scene has too few pairs ({full}) for the overflow test"
  assert not np.any(d.overflow.numpy() & int(OverflowType.BROADPHASE))
  sf.uninstall(m)

  sf.install(sim.mjm, m, sf.Options(broadphase=broadphase, max_collision_pairs=2))
  try:
    m.opt.warn_overflow = 0  # keep the printf quiet
  except (AttributeError, TypeError):
    pass
  d.overflow.zero_()
  sf.collision(m, d)
  overflow = d.overflow.numpy()
  got = plugin_pairs(m, d)
  stats = sf.get_collider(m).stats(d)
  for w in range(NWORLD):
    assert overflow[w] & int(OverflowType.BROADPHASE), f"world {w}: BROADPHASE overflow bit not set ({overflow[w]})"
    assert len(got[w]) <= 2, f"world {w}: {len(got[w])} pairs written with max_collision_pairs=2"
    assert stats["pairs_per_world"][w] == len(got[w])
    assert stats["dropped_pairs_per_world"][w] == full[w] - len(got[w]) > 0
  assert stats["pairs"] == sum(len(v) for v in got.values())
  sf.uninstall(m)


@pytest.mark.parametrize("broadphase", ["sap", "nxn"])
def test_overflow_only_in_crowded_world(overflow_scene, broadphase):
  """A world with few pairs keeps its budget and no overflow bit; a crowded one sets it."""
  sim = overflow_scene
  m, d = sim.m, sim.d
  q = np.stack([sim.mjm.qpos0.copy(), sim.mjm.qpos0.copy()])
  # world 1: lift every free body far apart from each other and off the floor
  for k, j in enumerate(np.nonzero(sim.mjm.jnt_type == mujoco.mjtJoint.mjJNT_FREE)[0]):
    adr = sim.mjm.jnt_qposadr[j]
    q[1, adr : adr + 3] = [2.0 * k, 5.0, 3.0]
  set_qpos(sim, q)
  sf.install(sim.mjm, m, sf.Options(broadphase=broadphase, max_collision_pairs=2))
  try:
    m.opt.warn_overflow = 0
  except (AttributeError, TypeError):
    pass
  d.overflow.zero_()
  sf.collision(m, d)
  overflow = d.overflow.numpy()
  stats = sf.get_collider(m).stats(d)
  assert overflow[0] & int(OverflowType.BROADPHASE)
  assert not overflow[1] & int(OverflowType.BROADPHASE)
  assert stats["dropped_pairs_per_world"][1] == 0
  assert stats["pairs_per_world"][1] == 0
  sf.uninstall(m)


@pytest.mark.parametrize("broadphase", ["sap", "nxn"])
def test_nonfinite_pose_skips_geom_in_its_world_only(broadphase):
  """A NaN pose in world 1 empties that geom's box there; world 0 is untouched and reported clean:
  the same pairs, and bitwise the same contacts.

  Pairs and contacts are compared as sets: with nxn every (world, pair) thread claims its place
  in the pair list with an atomic, so on a GPU the order differs between worlds and runs."""
  sim = load("convex_pile", nworld=NWORLD)
  mjm = sim.mjm
  sf.install(mjm, sim.m, sf.Options(broadphase=broadphase))
  q = np.stack([mjm.qpos0.copy(), mjm.qpos0.copy()])
  set_qpos(sim, q)
  sf.collision(sim.m, sim.d)
  before = plugin_pairs(sim.m, sim.d)
  assert sorted(before[0]) == sorted(before[1]) and before[0]
  mesh0 = int(mujoco.mj_name2id(mjm, mujoco.mjtObj.mjOBJ_GEOM, "mesh0"))
  assert any(mesh0 in p for p in before[1])
  adr = mjm.jnt_qposadr[mjm.body_jntadr[mjm.body("mesh0").id]]
  q[1, adr] = np.nan
  set_qpos(sim, q)
  sf.collision(sim.m, sim.d)
  after = plugin_pairs(sim.m, sim.d)
  stats = sf.get_collider(sim.m).stats(sim.d)
  assert stats["nonfinite_worlds"] == [1]
  assert sorted(after[0]) == sorted(before[0])
  assert not any(mesh0 in p for p in after[1])
  assert set(after[1]) == {p for p in before[1] if mesh0 not in p}
  # a second Data with the same history but a clean world 1 (the warm start remembers the first
  # call, so world 0 is compared with a world 0 that went through the same two calls)
  clean = mjw.put_data(mjm, sim.mjd, nworld=NWORLD)
  for _ in range(2):
    clean.qpos.assign(np.stack([mjm.qpos0, mjm.qpos0]).astype(np.float32))
    mjw.kinematics(sim.m, clean)
    sf.collision(sim.m, clean)
  isolated, reference = sorted_rows(world_contact_fields(sim.d, 0)), sorted_rows(world_contact_fields(clean, 0))
  assert isolated["dist"].size > 0
  for f in reference:
    assert np.array_equal(isolated[f], reference[f]), f
  sf.uninstall(sim.m)



@pytest.mark.parametrize("broadphase", ["sap", "nxn"])
@pytest.mark.parametrize("scene", ["primitives_plane", "convex_pile"])
def test_queues_deal_out_the_pair_list(scene, broadphase):
  """Each listed pair lands in its narrow-phase kernel's queue (analytic types, a sphere or
  capsule to GJK, other convex pairs to the MPR candidates), and sift_mpr_pairs keeps in the MPR
  queue every candidate but those without a contact."""

  rng = np.random.default_rng(5)
  sim = load(scene, nworld=NWORLD)
  collider = sf.install(sim.mjm, sim.m, sf.Options(broadphase=broadphase))
  qpos = np.stack([perturbed_qpos(sim.mjm, rng, 0.01, 0.2) for _ in range(NWORLD)])
  set_qpos(sim, qpos)
  sf.collision(sim.m, sim.d)
  st = collider.state(sim.m, sim.d)
  npair = int(st.broad.npair.numpy()[0])
  pair, worldid = st.broad.pair.numpy()[:npair], st.broad.pair_worldid.numpy()[:npair]
  count, queued = st.narrow.queue_count.numpy(), st.narrow.queue_pair.numpy()
  queue = {q: queued[q, : count[q]].tolist() for q in range(nph.NQUEUE)}
  for q, cids in queue.items():
    assert len(set(cids)) == len(cids) and all(0 <= c < npair for c in cids), f"queue {q}: {cids}"

  core = (GeomType.SPHERE, GeomType.CAPSULE)
  analytic = {tuple(sorted((int(a), int(b)))) for a, b in nph.ANALYTIC_PAIRS}
  for cid, (g1, g2) in enumerate(pair):
    t1, t2 = int(sim.mjm.geom_type[g1]), int(sim.mjm.geom_type[g2])
    if tuple(sorted((t1, t2))) in analytic:
      want = int(nph.QUEUE_ANALYTIC)
    elif t1 in core or t2 in core:
      want = int(nph.QUEUE_GJK)
    else:
      want = int(nph.QUEUE_CANDIDATE)
    got = [q for q in (nph.QUEUE_ANALYTIC, nph.QUEUE_GJK, nph.QUEUE_CANDIDATE) if cid in queue[int(q)]]
    assert got == [want], f"pair {cid} ({g1}, {g2}), types {t1} {t2}: queues {got}, expected {want}"

  mpr, candidates = set(queue[int(nph.QUEUE_MPR)]), set(queue[int(nph.QUEUE_CANDIDATE)])
  assert mpr and mpr <= candidates, f"MPR queue {sorted(mpr)} is empty or not among the candidates"
  touching = set()  # by the plugin or by MuJoCo C
  for w in range(NWORLD):
    touching |= {(w, *sorted(int(x) for x in g)) for g in contacts(sim.d, w).geom}
    touching |= {(w, *p) for p in mjc_pairs(sim.mjm, qpos[w])}
  assert any((int(worldid[c]), *sorted(int(x) for x in pair[c])) in touching for c in mpr)
  for cid in candidates - mpr:
    key = (int(worldid[cid]), *sorted(int(x) for x in pair[cid]))
    assert key not in touching, f"pair {key} was sifted out as apart, yet touches"
  sf.uninstall(sim.m)


def test_occupancy_is_asked_once_per_kernel_and_device(monkeypatch):
  """The listed-pairs launch on a GPU asks CUDA's occupancy once per kernel and device (a driver
  call a step otherwise), keyed so that Warp's Device, which is not hashable, can be a key."""
  import warp as wp

  from mjx_supportfield.stages import broadphase

  calls = []

  def suggested(kernel, device):
    calls.append((kernel, device.alias))
    return 128, 66

  monkeypatch.setattr(broadphase.wp, "get_suggested_block_size", suggested)
  monkeypatch.setattr(broadphase, "_FILLING_THREADS", {})
  device = wp.get_device("cpu")  # any Device: the CUDA one is as unhashable
  kernel = broadphase.update_aabbs
  assert broadphase._filling_threads(kernel, device) == 128 * 66
  assert broadphase._filling_threads(kernel, device) == 128 * 66
  assert calls == [(kernel, "cpu")]


@pytest.mark.parametrize("broadphase", ["sap", "nxn"])
def test_pair_order_changes_only_the_rows_order(monkeypatch, broadphase):
  """Pair by pair across the worlds (a GPU's default order) or world by world (the CPU's), the
  broad phase lists the same pairs and every world gets bitwise the same contacts, step after
  step (warm starts, the deep-pair check and the multi-contact pass included); only the order of
  the narrow phase's queues differs."""
  from mjx_supportfield.stages import broadphase as stage

  runs = {}
  for pair_major in (False, True):
    monkeypatch.setattr(stage, "PAIR_MAJOR", pair_major)
    rng = np.random.default_rng(11)
    sim = load("convex_pile", nworld=3)
    collider = sf.install(sim.mjm, sim.m, sf.Options(broadphase=broadphase))
    assert collider.broad.pair_major is pair_major
    set_qpos(sim, np.stack([perturbed_qpos(sim.mjm, rng, 0.01, 0.2) for _ in range(3)]))
    steps = []
    for _ in range(4):
      with bitwise_repeatable(sim.m):  # on a GPU the solver sums in atomic order
        mjw.step(sim.m, sim.d)
      st = collider.state(sim.m, sim.d)
      count, queued = st.narrow.queue_count.numpy(), st.narrow.queue_pair.numpy()
      npair = int(st.broad.npair.numpy()[0])
      pair, worldid = st.broad.pair.numpy()[:npair], st.broad.pair_worldid.numpy()[:npair]
      # each queue as (world, g1, g2) in its order
      queues = [[(int(worldid[c]), *map(int, pair[c])) for c in queued[q, : count[q]]] for q in range(len(count))]
      steps.append((queues, [sorted_rows(world_contact_fields(sim.d, w)) for w in range(3)]))
    runs[pair_major] = steps
    sf.uninstall(sim.m)
  reordered = False
  for (queues0, rows0), (queues1, rows1) in zip(runs[False], runs[True]):
    assert [sorted(q) for q in queues0] == [sorted(q) for q in queues1]
    reordered |= queues0 != queues1
    for w in range(3):
      assert rows0[w].keys() == rows1[w].keys()
      for k in rows0[w]:
        np.testing.assert_array_equal(rows0[w][k], rows1[w][k], err_msg=f"world {w}, contact field {k}")
  assert reordered  # the switch took


def test_pair_order_by_default():
  """Pair by pair only on a GPU, only for nxn, only for lists of at most PAIR_MAJOR_MAX_PAIRS."""
  from mjx_supportfield.stages.broadphase import PAIR_MAJOR_MAX_PAIRS
  from mjx_supportfield.stages.broadphase import pair_major_by_default

  assert pair_major_by_default(True, True, 37) and pair_major_by_default(True, True, PAIR_MAJOR_MAX_PAIRS)
  assert not pair_major_by_default(False, True, 37)  # the CPU keeps world by world
  assert not pair_major_by_default(True, False, 37)  # so does the sweep
  assert not pair_major_by_default(True, True, PAIR_MAJOR_MAX_PAIRS + 1)
