"""Models as users ship them: visual meshes of any size, colliding hulls larger than a support
field can name, per-world mesh variants and sizes (as mjlab's build_variant_model makes them),
model fields replaced per world after install (domain randomisation), and a Data made for
another model."""

import logging

import mujoco
import mujoco_warp as mjw
import numpy as np
import pytest
import warp as wp
from conftest import ROOT
from conftest import angle_deg
from conftest import contact_table
from conftest import contacts

import mjx_supportfield as sf
from mjx_supportfield.geometry.support_field import MAX_HULL

MESHES = f"{ROOT}/tests/data/repro/meshes"


def _sphere_points(n: int, radius: float) -> str:
  """``n`` points on a sphere as an MJCF vertex list: a hull of about ``n`` vertices."""
  p = np.random.default_rng(0).normal(size=(n, 3))
  p *= radius / np.linalg.norm(p, axis=1, keepdims=True)
  return " ".join(f"{x:.6f}" for x in p.ravel())


BIG = MAX_HULL + 2000
BIG_MESHES = f"""
<mujoco>
  <asset>
    <mesh name="scan" vertex="{_sphere_points(BIG, 0.1)}"/>
    <mesh name="shell" vertex="{_sphere_points(BIG, 0.05)}"/>
  </asset>
  <worldbody>
    <geom name="floor" type="plane" size="1 1 .1"/>
    <body name="robot" pos="0 0 .0495"><freejoint/>
      <geom name="trunk_visual" type="mesh" mesh="scan" contype="0" conaffinity="0"/>
      <geom name="trunk" type="box" size=".05 .05 .05"/>
    </body>
    <body name="ball" pos=".3 0 .0495"><freejoint/><geom name="shell" type="mesh" mesh="shell"/></body>
    <body name="cube" pos=".3 0 .148"><freejoint/><geom name="cube" type="box" size=".05 .05 .05"/></body>
  </worldbody>
</mujoco>
"""


@pytest.fixture(scope="module")
def big_meshes():
  return mujoco.MjModel.from_xml_string(BIG_MESHES)


def _pair_tables(mjm, nworld=2, options=None, install=True):
  mjd = mujoco.MjData(mjm)
  mujoco.mj_forward(mjm, mjd)
  m = mjw.put_model(mjm)
  d = mjw.put_data(mjm, mjd, nworld=nworld, naconmax=64 * nworld)
  collider = sf.install(mjm, m, options) if install else None
  mjw.collision(m, d) if not install else sf.collision(m, d)
  return collider, m, d


def test_visual_meshes_of_any_size_get_nothing(big_meshes, caplog):
  """A visual mesh (contype = conaffinity = 0, in no pair) with a hull past a field's reach
  installs, and gets no hull, field or polygons; the colliding hull as large goes to MuJoCo
  Warp's narrow phase with one note naming it, and every world gets stock's contacts."""
  mjm = big_meshes
  scan, shell = (mujoco.mj_name2id(mjm, mujoco.mjtObj.mjOBJ_MESH, n) for n in ("scan", "shell"))
  assert min(int(mjm.mesh_graph[mjm.mesh_graphadr[i]]) for i in (scan, shell)) > MAX_HULL
  with caplog.at_level(logging.INFO, logger="mjx_supportfield"):
    collider, m, d = _pair_tables(mjm)
  notes = [r.getMessage() for r in caplog.records if "own narrow phase" in r.getMessage()]
  assert len(notes) == 1 and "'shell'" in notes[0] and "trunk_visual" not in notes[0]
  assert collider.collided_meshes == []
  assert collider.mesh_support.hull_num.numpy().tolist() == [0, 0]
  assert collider.mesh_support.field.shape[0] == 1 and collider.mesh_support.poly_pos.shape[0] <= 1
  _, ms, ds = _pair_tables(mjm, install=False)
  for w in range(d.nworld):
    mine, stock = contact_table(d, w), contact_table(ds, w)
    assert set(mine) == set(stock) and len(mine) == 3  # trunk, ball and cube on their neighbours
    for pair, (dist, normal, _) in stock.items():
      assert abs(mine[pair][0] - dist) < 1e-6 and angle_deg(mine[pair][1], normal) < 1e-3


def test_a_visual_mesh_leaves_the_colliding_ones_alone():
  """Only the meshes of geoms in some pair get support: a pile with a visual copy of its meshes
  builds exactly the colliding meshes' fields."""
  xml = f"""
  <mujoco><compiler meshdir="{MESHES}"/>
    <asset><mesh name="die" file="die.obj" scale=".018 .018 .018"/>
           <mesh name="dodeca" file="dodecahedron.stl" scale=".0014 .0014 .0014"/></asset>
    <worldbody><geom type="plane" size="1 1 .1"/>
      <body pos="0 0 .05"><freejoint/><geom type="mesh" mesh="die"/>
        <geom type="mesh" mesh="dodeca" contype="0" conaffinity="0" group="2"/></body>
    </worldbody>
  </mujoco>"""
  mjm = mujoco.MjModel.from_xml_string(xml)
  collider = sf.install(mjm, mjw.put_model(mjm))
  assert collider.collided_meshes == [0]
  assert collider.mesh_support.hull_num.numpy()[1] == 0 and collider.mesh_support.hull_num.numpy()[0] > 0


VARIANT_XML = """
<mujoco><compiler meshdir="{meshes}"/>
  <asset><mesh name="die" file="die.obj" scale=".018 .018 .018"/>
         <mesh name="dodeca" file="dodecahedron.stl" scale=".0014 .0014 .0014"/>
         <mesh name="tetra" file="tetrahedron.stl" scale=".016 .016 .016"/></asset>
  <worldbody><geom name="floor" type="plane" size="1 1 .1"/>
    <body name="a" pos="0 0 .1"><freejoint/><geom name="slot_a" type="mesh" mesh="{a}"/></body>
    <body name="b" pos=".004 .002 .15"><freejoint/><geom name="slot_b" type="mesh" mesh="{b}"/></body>
    <body name="c" pos="-.003 .001 .25"><freejoint/><geom name="box" type="box" size="{s} {s} {s}"/></body>
  </worldbody>
</mujoco>"""
# per world: the slots' meshes (None: the slot is empty in that world) and the box's half size
VARIANTS = [("die", "tetra", 0.02), ("dodeca", None, 0.03), ("tetra", "die", 0.015)]


def _variant(a, b, s) -> mujoco.MjModel:
  return mujoco.MjModel.from_xml_string(VARIANT_XML.format(meshes=MESHES, a=a, b=b or "die", s=s))


def _z_extent(mjm, mjd, g):
  if mjm.geom_type[g] == mujoco.mjtGeom.mjGEOM_MESH:
    i = mjm.geom_dataid[g]
    v = mjm.mesh_vert[mjm.mesh_vertadr[i]:mjm.mesh_vertadr[i] + mjm.mesh_vertnum[i]]
  else:
    v = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)]) * mjm.geom_size[g]
  z = (v @ mjd.geom_xmat[g].reshape(3, 3).T)[:, 2] + mjd.geom_xpos[g][2]
  return z.min(), z.max()


def _stacked(mjm, with_b: bool) -> mujoco.MjData:
  """The bodies stacked on the floor, each sunk 0.5 mm into the one below."""
  mjd = mujoco.MjData(mjm)
  mujoco.mj_forward(mjm, mjd)
  top = 0.0
  for g in (1, 2, 3):
    if g == 2 and not with_b:
      continue
    adr = mjm.jnt_qposadr[mjm.body_jntadr[g]]
    mjd.qpos[adr + 2] += top - _z_extent(mjm, mjd, g)[0] - 5e-4
    mujoco.mj_forward(mjm, mjd)
    top = _z_extent(mjm, mjd, g)[1]
  return mjd


def _variant_batch(base, models):
  """A Model of ``base`` with each world's meshes, sizes, bounds and geom frames from its own
  compile, as mjlab's build_variant_model sets them, and a Data with each world's stack."""
  m = mjw.put_model(base)
  dataid = np.stack([mv.geom_dataid for mv in models])
  for w, (_, b, _) in enumerate(VARIANTS):
    if b is None:
      dataid[w, 2] = -1  # the slot is empty in this world
  m.geom_dataid = wp.array(dataid, dtype=int)
  for f in ("geom_size", "geom_rbound", "geom_pos", "geom_quat"):
    setattr(m, f, wp.array(np.stack([getattr(mv, f) for mv in models]).astype(np.float32), dtype=getattr(m, f).dtype))
  m.geom_aabb = wp.array(np.stack([mv.geom_aabb.reshape(-1, 2, 3) for mv in models]).astype(np.float32), dtype=wp.vec3)
  d = mjw.put_data(base, mujoco.MjData(base), nworld=len(models), naconmax=64 * len(models))
  d.qpos.assign(np.stack([_stacked(mv, v[1] is not None).qpos for mv, v in zip(models, VARIANTS)]).astype(np.float32))
  mjw.kinematics(m, d)
  return m, d


def test_per_world_meshes_and_sizes_get_each_worlds_contacts():
  """Worlds holding different meshes (one slot empty in one world) and box sizes: each world's
  contacts are stock's for that world, pair by pair, and touch the pairs MuJoCo C finds on that
  world's own compile."""
  models = [_variant(*v) for v in VARIANTS]
  base = _variant("die", "die", 0.02)
  m, d = _variant_batch(base, models)
  collider = sf.install(base, m)
  assert collider.collided_meshes == [0, 1, 2]  # every world's meshes, not only the compiled ones
  sf.collision(m, d)
  ms, ds = _variant_batch(base, models)
  mjw.collision(ms, ds)
  for w, (mv, v) in enumerate(zip(models, VARIANTS)):
    mine, stock = contact_table(d, w), contact_table(ds, w)
    mjd = _stacked(mv, v[1] is not None)
    ref = {tuple(sorted((int(c.geom1), int(c.geom2)))) for c in mjd.contact[: mjd.ncon]}
    assert set(mine) == set(stock) == ref, (w, v)
    for pair, (dist, normal, _) in stock.items():
      assert abs(mine[pair][0] - dist) < 1e-5 and angle_deg(mine[pair][1], normal) < 1.0, (w, pair)


def test_geom_dataid_replaced_after_install_is_checked():
  """A per-world mesh assignment set after install that names a mesh install built nothing for
  is refused naming the geom, world and mesh; one within the built meshes is taken."""
  models = [_variant(*v) for v in VARIANTS]
  base = _variant("die", "die", 0.02)
  m, d = _variant_batch(base, models)
  sf.install(base, m)
  sf.collision(m, d)
  m.geom_dataid = wp.array(np.asarray(m.geom_dataid.numpy())[::-1].copy(), dtype=int)  # the worlds' meshes swapped
  sf.collision(m, d)
  assert contacts(d, 0).n > 0
  only_die = _variant("die", "die", 0.02)
  m2 = mjw.put_model(only_die)
  sf.install(only_die, m2)
  d2 = mjw.put_data(only_die, mujoco.MjData(only_die), nworld=2)
  m2.geom_dataid = wp.array(np.array([[-1, 0, 0, -1], [-1, 0, 2, -1]]), dtype=int)
  with pytest.raises(ValueError, match=r"geom_dataid .*geom 'slot_b' names mesh 2 in world 1"):
    sf.collision(m2, d2)


def test_fields_randomised_per_world_after_install():
  """Friction, solref and a box's size expanded to one value a world after install, as mjlab's
  domain randomisation does: each world's contacts carry its own, as stock's do."""
  mjm = _variant("die", "tetra", 0.02)
  mjd = _stacked(mjm, True)
  out = {}
  for impl in ("plugin", "stock"):
    m = mjw.put_model(mjm)
    d = mjw.put_data(mjm, mjd, nworld=3, naconmax=3 * 64)
    if impl == "plugin":
      sf.install(mjm, m)
      sf.collision(m, d)  # once on the fields as compiled
    friction = np.tile(mjm.geom_friction, (3, 1, 1)).astype(np.float32)
    friction[:, :, 0] = np.array([0.3, 0.7, 1.1])[:, None]
    m.geom_friction = wp.array(friction, dtype=wp.vec3)
    solref = np.tile(mjm.geom_solref, (3, 1, 1)).astype(np.float32)
    solref[1, :, 0] = 0.05
    m.geom_solref = wp.array(solref, dtype=wp.vec2)
    size = np.tile(mjm.geom_size, (3, 1, 1)).astype(np.float32)
    size[2, 3] *= 1.05  # the box sinks 1 mm deeper into the tetrahedron below it in world 2
    rbound = np.tile(mjm.geom_rbound, (3, 1)).astype(np.float32)
    rbound[2, 3] *= 1.05
    aabb = np.tile(mjm.geom_aabb.reshape(-1, 2, 3), (3, 1, 1, 1)).astype(np.float32)
    aabb[2, 3, 1] *= 1.05
    m.geom_size = wp.array(size, dtype=wp.vec3)
    m.geom_rbound = wp.array(rbound, dtype=float)
    m.geom_aabb = wp.array(aabb, dtype=wp.vec3)
    mjw.kinematics(m, d)
    sf.collision(m, d) if impl == "plugin" else mjw.collision(m, d)
    n = int(d.nacon.numpy()[0])
    c = d.contact
    out[impl] = {w: sorted((tuple(sorted(int(x) for x in c.geom.numpy()[i])), round(float(c.friction.numpy()[i][0]), 4),
                            round(float(c.solref.numpy()[i][0]), 4), round(float(c.dist.numpy()[i]), 5))
                           for i in range(n) if c.worldid.numpy()[i] == w) for w in range(3)}
  for w in range(3):
    mine = {(g, f, s) for g, f, s, _ in out["plugin"][w]}
    assert mine == {(g, f, s) for g, f, s, _ in out["stock"][w]}, w
  assert {f for _, f, _, _ in out["plugin"][1]} >= {0.7}
  assert min(dist for g, _, _, dist in out["plugin"][2] if g == (2, 3)) < min(
    dist for g, _, _, dist in out["plugin"][0] if g == (2, 3)) - 5e-4


SEVEN_DOF = """
<mujoco><worldbody><geom type="plane" size="1 1 .1"/>
  <body pos="0 0 .1">{joints}<geom type="box" size=".05 .05 .05"/></body></worldbody></mujoco>"""


def test_data_of_another_model_with_the_same_geoms_is_refused():
  """Two models with the same geoms, bodies, qpos and qvel sizes but other joints (a free joint,
  a ball and three slides): the Data of one is refused for the other, naming the field that
  differs."""
  free = mujoco.MjModel.from_xml_string(SEVEN_DOF.format(joints="<freejoint/>"))
  ball = mujoco.MjModel.from_xml_string(SEVEN_DOF.format(
    joints='<joint type="ball"/>' + "".join(f'<joint type="slide" axis="{a}"/>' for a in ("1 0 0", "0 1 0", "0 0 1"))))
  assert (free.ngeom, free.nbody, free.nq, free.nv) == (ball.ngeom, ball.nbody, ball.nq, ball.nv)
  m = mjw.put_model(free)
  sf.install(free, m)
  d = mjw.make_data(ball, nworld=2)
  with pytest.raises(ValueError, match=r"Data\.xanchor has shape \(2, 4\) but the model needs \(nworld, 1\).*another"):
    sf.collision(m, d)
