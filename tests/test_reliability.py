"""Reliability (issue #7): bad input, degenerate geometry, non-finite state, overflow, determinism
and sleeping. What test_install / test_broadphase / test_options / test_cli already cover
(installing twice, uninstalling a stock model, basic Options errors, broad-phase overflow through
``collision``, one NaN body) is not repeated here.

Scenes are small MJCF strings made of mesh geoms (plus a floor where stepping needs one), so
the plugin's MPR kernel and the analytic plane-mesh kernel that other tests compile are reused.
"""

import mujoco
import mujoco_warp as mjw
import numpy as np
import pytest
import warp as wp
from mujoco_warp._src.types import DeterminismType
from mujoco_warp._src.types import OverflowType

import mjx_supportfield as sf
from conftest import bitwise_repeatable
from conftest import on_gpu
from conftest import printed
from conftest import sorted_rows
from conftest import world_contact_fields
from conftest import angle_deg
from conftest import contact_table
from conftest import contacts
from conftest import load
from conftest import load_mjmodel
from conftest import mjc_contact_table
from mjx_supportfield.launch import contact_sort
from mjx_supportfield.tools.bench import settled_state
from mjx_supportfield.tools.cli import main as cli_main

NWORLD = 3


def cube_verts(half: float = 0.05) -> np.ndarray:
  """The 8 corners of a cube of half-size ``half``."""
  return half * np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)], dtype=float)


def vertex_attr(verts) -> str:
  return " ".join(f"{x:.9g}" for x in np.ravel(verts))


def geom_name_id(mjm, name: str) -> int:
  return int(mujoco.mj_name2id(mjm, mujoco.mjtObj.mjOBJ_GEOM, name))


all_contacts = contact_sort.host_contacts


def same_arrays(a: dict, b: dict) -> bool:
  return a.keys() == b.keys() and all(np.array_equal(a[k], b[k]) for k in a)


@pytest.fixture(scope="module")
def pile():
  """convex_pile (floor + six hulls, NWORLD worlds) with the plugin installed."""
  sim = load("convex_pile", nworld=NWORLD)
  sf.install(sim.mjm, sim.m)
  yield sim
  if sf.get_collider(sim.m) is not None:
    sf.uninstall(sim.m)


def quiet_overflow(m):
  """No printed overflow warnings from this model (d.overflow bits are still set)."""
  m.opt.warn_overflow = 0


# --- 1. bad input ------------------------------------------------------------------------------

FLOOR_SCENE = """<mujoco><asset><mesh name="m" {mesh}/></asset><worldbody>
  <geom name="floor" type="plane" size="1 1 .1"/>
  <body pos="0 0 .2"><freejoint/><geom name="g" type="{gtype}" {geom}/></body></worldbody></mujoco>"""

# (label, mesh attributes, geom type, geom attributes, words of MuJoCo's compiler error)
REJECTED = [
  ("coplanar", 'vertex="0 0 0 1 0 0 0 1 0 1 1 0"', "mesh", 'mesh="m"', "coplanar"),
  ("collinear", 'vertex="0 0 0 1 0 0 2 0 0 3 0 0"', "mesh", 'mesh="m"', "collinear"),
  ("colocated", 'vertex="0 0 0 0 0 0 0 0 0 0 0 0"', "mesh", 'mesh="m"', "colocated"),
  ("three_points", 'vertex="0 0 0 1 0 0 0 1 0"', "mesh", 'mesh="m"', "at least 4 vertices"),
  ("nan_vertex", 'vertex="0 0 0 1 0 0 0 1 0 0 0 nan"', "mesh", 'mesh="m"', "not finite"),
  ("zero_scale", 'vertex="0 0 0 1 0 0 0 1 0 0 0 1" scale="0 1 1"', "mesh", 'mesh="m"', "volume is too small"),
  ("missing_file", 'file="no_such_mesh.obj"', "mesh", 'mesh="m"', "no_such_mesh.obj"),
  ("zero_size_sphere", 'vertex="0 0 0 1 0 0 0 1 0 0 0 1"', "sphere", 'size="0"', "size 0 must be positive"),
  ("zero_size_box", 'vertex="0 0 0 1 0 0 0 1 0 0 0 1"', "box", 'size="0 .1 .1"', "must be positive"),
]


@pytest.mark.parametrize("label,mesh,gtype,geom,needle", REJECTED, ids=[r[0] for r in REJECTED])
def test_compiler_rejects_degenerate_input_in_one_cli_line(tmp_path, monkeypatch, capsys, label, mesh, gtype, geom,
                                                            needle):
  """Meshes MuJoCo's compiler refuses (flat, collinear, colocated, < 4 points, non-finite, zero
  volume, missing file) and zero-size geoms: `compare` exits 2 with one error line naming it."""
  monkeypatch.chdir(tmp_path)  # MuJoCo logs the NaN warning to MUJOCO_LOG.TXT in the working directory
  path = tmp_path / f"{label}.xml"
  path.write_text(FLOOR_SCENE.format(mesh=mesh, gtype=gtype, geom=geom))
  with pytest.raises(ValueError):
    mujoco.MjModel.from_xml_path(str(path))  # the compiler's own verdict
  rc = cli_main(["compare", str(path), "--steps", "1", "--samples", "1"])
  err = capsys.readouterr().err
  lines = [x for x in err.splitlines() if x.startswith("mjx-supportfield")]
  assert rc == 2
  assert len(lines) == 1 and needle in lines[0] and str(path) in lines[0], err


OPTIONS_OUT_OF_RANGE = [
  ("max_contacts_per_pair", 0),
  ("max_contacts_per_pair", 6),
  ("mc_perturbation", 0.0),
  ("mc_perturbation", 1.0),
  ("mc_perturbation", float("nan")),
  ("mc_tolerance", -0.1),
  ("mc_tolerance", 0.6),
  ("mpr_to_sdf_overlap_ratio", -1.0),
  ("mpr_to_sdf_overlap_ratio", float("inf")),
  ("sdf_res", 4),
  ("sdf_res", 1000),
  ("sdf_res", 32.0),
  ("mpr_refine", -1),
  ("mpr_refine", 33),
  ("mpr_iterations", 10_001),
  ("max_collision_pairs", 1 << 25),
]


@pytest.mark.parametrize("field,value", OPTIONS_OUT_OF_RANGE, ids=[f"{f}={v!r}" for f, v in OPTIONS_OUT_OF_RANGE])
def test_options_out_of_range_name_the_field(field, value):
  """The fields test_options does not try: each bad value is a ValueError naming the field."""
  with pytest.raises(ValueError, match=f"Options.{field}"):
    sf.Options(**{field: value})


def test_install_with_bad_option_leaves_model_stock(pile):
  sim = pile
  sf.uninstall(sim.m)
  try:
    with pytest.raises(ValueError, match="Options.mc_tolerance"):
      sf.install(sim.mjm, sim.m, {"mc_tolerance": -1.0})
    assert sf.get_collider(sim.m) is None
  finally:
    sf.install(sim.mjm, sim.m)


@pytest.mark.parametrize(
  "field,index,value,needle",
  [
    ("geom_size", (0, "mesh0", 0), np.nan, "geom 'mesh0': geom_size"),
    ("geom_margin", (0, "mesh2"), np.inf, "geom 'mesh2': geom_margin"),
    ("geom_gap", (0, "floor"), np.nan, "geom 'floor': geom_gap"),
    ("geom_rbound", (0, "mesh1"), np.nan, "geom 'mesh1': geom_rbound"),
    ("mesh_vert", ("vert", 3, 1), np.nan, "mesh_vert"),
  ],
)
def test_nonfinite_model_values_raise_naming_geom(pile, field, index, value, needle):
  """Values edited after compiling (MuJoCo's checks are bypassed): install names geom and field."""
  sim = pile
  arr = getattr(sim.m, field)
  saved = arr.numpy().copy()
  bad = saved.copy()
  if index[0] == "vert":
    bad[int(sim.mjm.mesh_vertadr[index[1]]), index[2]] = value
    needle = f"mesh '{sim.mjm.mesh(index[1]).name}': " + needle
  else:
    bad[(index[0], geom_name_id(sim.mjm, index[1])) + index[2:]] = value
  sf.uninstall(sim.m)
  arr.assign(bad)
  try:
    with pytest.raises(ValueError, match=needle):
      sf.install(sim.mjm, sim.m)
    assert sf.get_collider(sim.m) is None
  finally:
    arr.assign(saved)
    sf.install(sim.mjm, sim.m)


def test_negative_primitive_size_raises():
  sim = load("""<mujoco><worldbody><body><freejoint/><geom name="ball" size=".1"/></body>
    <geom name="slab" type="box" size="1 1 .1" pos="0 0 -.2"/></worldbody></mujoco>""")
  size = sim.m.geom_size.numpy()
  size[0, geom_name_id(sim.mjm, "ball"), 0] = -0.1
  sim.m.geom_size.assign(size)
  with pytest.raises(ValueError, match="geom 'ball': geom_size"):
    sf.install(sim.mjm, sim.m)


def test_data_of_another_model_names_the_field():
  """Same geoms, another joint: the dispatcher (mjw.collision) refuses the Data, naming qpos."""
  body = '<body pos="0 0 .3"><joint type="{}"/><geom name="b" type="mesh" mesh="cube"/></body>'
  xml = (f'<mujoco><asset><mesh name="cube" vertex="{vertex_attr(cube_verts())}"/></asset><worldbody>'
         '<geom name="floor" type="plane" size="1 1 .1"/>{}</worldbody></mujoco>')
  sim = load(xml.format(body.format("free")))
  other = load(xml.format(body.format("slide")))  # nq 1 against 7, same ngeom and nbody
  sf.install(sim.mjm, sim.m)
  with pytest.raises(ValueError, match=r"Data\.qpos .*another model"):
    mjw.collision(sim.m, other.d)
  mjw.collision(sim.m, sim.d)  # its own Data still works
  assert contacts(sim.d, 0).n == 0  # the cube hangs 0.25 m above the floor


def test_strided_contact_array_is_refused_naming_it():
  """The contact writers address rows through pointers: a Data whose contact array is a strided
  view (not what make_data or put_data make) is refused at its first collision, naming the field,
  instead of having rows written past the view."""
  sim = load("convex_pile", nworld=2)
  sf.install(sim.mjm, sim.m)
  dist = sim.d.contact.dist
  sim.d.contact.dist = wp.zeros(2 * dist.shape[0], dtype=float, device=dist.device)[::2]
  with pytest.raises(ValueError, match=r"Data\.contact\.dist is not contiguous"):
    mjw.collision(sim.m, sim.d)


# --- degenerate meshes MuJoCo accepts, zero sizes, extreme scales ---------------------------------

# static degenerate hulls, 0.5 m apart along x; a free cube probe overlaps each by 1 mm
DEGENERATE = {
  # 4 corners of a 10 cm square and a centre 1 um above it: a pyramid 1e-5 of its width tall
  "sliver": [[-0.05, -0.05, 0], [0.05, -0.05, 0], [-0.05, 0.05, 0], [0.05, 0.05, 0], [0, 0, 1e-6]],
  # a tetrahedron with every vertex three times
  "repeated": [[-0.05, -0.05, 0], [0.05, -0.05, 0], [0, 0.05, 0], [0, 0, 0.05]] * 3,
  # a 20 cm needle, 1 um thick
  "needle": [[-0.1, 0, 0], [0.1, 0, 0], [0, 1e-6, 0], [0, 0, 1e-6]],
}


def degenerate_scene() -> str:
  assets = "".join(f'<mesh name="{k}" vertex="{vertex_attr(v)}"/>' for k, v in DEGENERATE.items())
  assets += f'<mesh name="cube" vertex="{vertex_attr(cube_verts())}"/>'
  bodies = ""
  for i, k in enumerate(DEGENERATE):
    x = 0.5 * i
    top = max(p[2] for p in DEGENERATE[k])
    bodies += f'<geom name="{k}" type="mesh" mesh="{k}" pos="{x} 0 0"/>'
    # the probe's lowest face 1 mm below the hull's top (the sliver's apex, the needle, the tetra's tip)
    bodies += (f'<body name="probe_{k}" pos="{x} 0.01 {top + 0.05 - 0.001}"><freejoint/>'
               f'<geom name="probe_{k}" type="mesh" mesh="cube"/></body>')
  return f'<mujoco><option gravity="0 0 0"/><asset>{assets}</asset><worldbody>{bodies}</worldbody></mujoco>'


def check_against_mujoco(sim, pairs, depth_tol, angle_tol):
  """Each named pair has a contact in world 0 as in MuJoCo C: depth and normal within tolerance."""
  mjc = mjc_contact_table(sim.mjm, sim.mjd)
  got = contact_table(sim.d, 0)
  c = contacts(sim.d, 0)
  assert np.all(np.isfinite(c.dist)) and np.all(np.isfinite(c.frame)) and np.all(np.isfinite(c.pos))
  np.testing.assert_allclose(np.linalg.norm(c.normal, axis=1), 1.0, atol=1e-5)
  for a, b in pairs:
    key = tuple(sorted((geom_name_id(sim.mjm, a), geom_name_id(sim.mjm, b))))
    assert key in mjc, f"{a}-{b}: MuJoCo C finds no contact; the scene is wrong"
    assert key in got, f"{a}-{b}: no plugin contact (MuJoCo C: dist {mjc[key][0]:.3g})"
    assert abs(got[key][0] - mjc[key][0]) <= depth_tol, f"{a}-{b}: dist {got[key][0]:.6g}, MuJoCo C {mjc[key][0]:.6g}"
    assert angle_deg(got[key][1], mjc[key][1]) <= angle_tol, f"{a}-{b}: normal {got[key][1]} vs {mjc[key][1]}"


def test_degenerate_meshes_mujoco_accepts():
  """A 1e-5-thin sliver, repeated vertices and a needle compile in MuJoCo; install works and each
  gives MuJoCo C's contact (1 mm deep, normal up); stepping stays finite."""
  sim = load(degenerate_scene())
  sf.install(sim.mjm, sim.m)
  sf.collision(sim.m, sim.d)
  check_against_mujoco(sim, [(k, f"probe_{k}") for k in DEGENERATE], depth_tol=2e-5, angle_tol=1.0)
  for _ in range(3):
    mjw.step(sim.m, sim.d)
  assert np.all(np.isfinite(sim.d.qpos.numpy()))
  assert len(contacts(sim.d, 0).dist) >= len(DEGENERATE)


ZERO_SIZE_SCENE = """<mujoco><option gravity="0 0 0"/><asset><mesh name="cube" vertex="{cube}"/></asset><worldbody>
  <geom name="block" type="mesh" mesh="cube" contype="1" conaffinity="1"/>
  <body pos="-.02 0 .048"><freejoint/><geom name="ball" size=".01" contype="2" conaffinity="1"/></body>
  <body pos=".02 0 .048"><freejoint/><geom name="pill" type="capsule" size=".01 .01" contype="2" conaffinity="1"/>
  </body></worldbody></mujoco>"""


def test_zero_size_primitives_after_compile():
  """Radii set to 0 after compiling: a point (sphere) and a segment (capsule) 2 mm inside a cube
  mesh: MuJoCo C's contacts (2 mm and 12 mm deep), no NaN."""
  mjm = mujoco.MjModel.from_xml_string(ZERO_SIZE_SCENE.format(cube=vertex_attr(cube_verts())))
  mjm.geom_size[geom_name_id(mjm, "ball"), 0] = 0.0
  mjm.geom_size[geom_name_id(mjm, "pill"), 0] = 0.0
  sim = load(None, mjm=mjm)
  sf.install(sim.mjm, sim.m)
  sf.collision(sim.m, sim.d)
  check_against_mujoco(sim, [("block", "ball"), ("block", "pill")], depth_tol=1e-5, angle_tol=0.5)


def scaled_scene(s: float, mass: float) -> str:
  """A static cube (half-size s), a free cube on it turned 20 deg and a ball against its side,
  each overlapping it by 1 % of s; a tetrahedron's tip pokes 1 % of s into its bottom face."""
  tetra = s * np.array([[0, 0, 0], [-0.2, -0.2, -0.5], [0.3, -0.1, -0.5], [-0.1, 0.3, -0.5]])
  return f"""<mujoco><option gravity="0 0 0"/><asset>
    <mesh name="cube" vertex="{vertex_attr(cube_verts(s))}"/><mesh name="tetra" vertex="{vertex_attr(tetra)}"/>
    </asset><worldbody><geom name="base" type="mesh" mesh="cube"/>
    <body pos="0 0 {1.99 * s}" euler="0 0 20"><freejoint/>
      <geom name="top" type="mesh" mesh="cube" mass="{mass}"/></body>
    <body pos="{1.49 * s} 0 0"><freejoint/><geom name="ball" size="{0.5 * s}" mass="{mass}"/></body>
    <body pos="{0.8 * s} {0.8 * s} {-0.99 * s}"><freejoint/><geom name="poke" type="mesh" mesh="tetra" mass="{mass}"/>
    </body></worldbody></mujoco>"""


@pytest.mark.parametrize("scale", [1e-4, 1e3])
def test_extreme_scales(scale):
  """The same scene at 0.1 mm and at 1 km: depths within 1e-4 x the scene size of MuJoCo C's
  (1 % of the 1 % overlaps), normals within 1 deg, and steps stay finite."""
  sim = load(scaled_scene(scale, mass=1e-3 if scale < 1 else 1e6))
  sf.install(sim.mjm, sim.m)
  sf.collision(sim.m, sim.d)
  check_against_mujoco(sim, [("base", "top"), ("base", "ball"), ("base", "poke")], depth_tol=1e-4 * scale,
                       angle_tol=1.0)
  for _ in range(2):
    mjw.step(sim.m, sim.d)
  assert np.all(np.isfinite(sim.d.qpos.numpy()))


# --- 2. non-finite state ---------------------------------------------------------------------------


def free_qpos_adr(mjm, body: str) -> int:
  return int(mjm.jnt_qposadr[mjm.body_jntadr[mjm.body(body).id]])


def test_nonfinite_world_is_flagged_and_isolated(pile):
  """World 1's qpos all NaN, world 2 one body at +inf: those worlds are flagged (stats), world 1
  gets no contacts, no contact holds NaN, and world 0 steps bit for bit like a clean Data's."""
  sim = pile
  m, mjm = sim.m, sim.mjm
  with bitwise_repeatable(m):
    _nonfinite_world_is_flagged_and_isolated(m, mjm)


def _nonfinite_world_is_flagged_and_isolated(m, mjm):
  ref = mjw.make_data(mjm, nworld=NWORLD)
  bad = mjw.make_data(mjm, nworld=NWORLD)
  q = bad.qpos.numpy()
  q[1] = np.nan
  q[2, free_qpos_adr(mjm, "mesh3") + 2] = np.inf
  bad.qpos.assign(q)
  mesh3 = geom_name_id(mjm, "mesh3")
  for _ in range(3):
    mjw.step(m, ref)
    mjw.step(m, bad)
    assert sf.get_collider(m).stats(bad)["nonfinite_worlds"] == [1, 2]
    assert sf.get_collider(m).stats(ref)["nonfinite_worlds"] == []
    assert contacts(bad, 1).n == 0
    c2 = contacts(bad, 2)
    assert not np.any(c2.geom == mesh3)
    c0, r0 = contacts(bad, 0), contacts(ref, 0)
    assert c0.n > 0
    for f in ("dist", "pos", "frame", "geom"):
      assert np.array_equal(getattr(c0, f), getattr(r0, f)), f
    stored = all_contacts(bad)
    for f in ("dist", "pos", "frame", "friction", "solref", "solimp"):
      assert np.all(np.isfinite(stored[f])), f
  assert np.array_equal(bad.qpos.numpy()[0], ref.qpos.numpy()[0])
  # the user resets the broken worlds: the flag clears and contacts come back
  mjw.reset_data(m, bad, wp.array([False, True, True], dtype=bool))
  mjw.step(m, bad)
  assert sf.get_collider(m).stats(bad)["nonfinite_worlds"] == []
  assert contacts(bad, 1).n > 0 and contacts(bad, 2).n > 0


def test_pair_overflow_in_one_world_leaves_the_others_bitwise_unchanged():
  """World 1 has all six hulls piled into one spot (every pair overlaps) and overflows
  max_collision_pairs; world 0, at rest, keeps bitwise the contacts it has beside a clean world."""
  sim = load("convex_pile", nworld=2)
  mjm, m = sim.mjm, sim.m
  resting = perturbed_pile_qpos(mjm, 0)[0]
  piled = resting.copy()
  for i in range(6):
    piled[free_qpos_adr(mjm, f"mesh{i}") : free_qpos_adr(mjm, f"mesh{i}") + 3] = (0.0, 0.0, 0.3 + 0.01 * i)
  quiet_overflow(m)

  def run(options, other):
    collider = sf.install(mjm, m, options)
    d = mjw.put_data(mjm, sim.mjd, nworld=2)
    d.qpos.assign(np.stack([resting, other]).astype(np.float32))
    mjw.kinematics(m, d)
    sf.collision(m, d)
    stats, fields = collider.stats(d), sorted_rows(world_contact_fields(d, 0))
    sf.uninstall(m)
    return stats, fields

  npair = run(sf.Options(), piled)[0]["pairs_per_world"]
  assert npair[1] > npair[0] > 0
  budget = sf.Options(max_collision_pairs=npair[0])  # world 0's pairs fit, world 1's do not
  (clean_stats, clean), (stats, isolated) = run(budget, resting), run(budget, piled)
  assert clean_stats["dropped_pairs_per_world"] == [0, 0]
  assert stats["dropped_pairs_per_world"][0] == 0 and stats["dropped_pairs_per_world"][1] > 0
  assert clean["dist"].size > 0
  for f in clean:
    assert np.array_equal(isolated[f], clean[f]), f



def test_contact_overflow_in_one_world_leaves_the_others_bitwise_unchanged():
  """Options.contacts_per_world: world 0 has all six hulls piled into one spot and finds more
  contacts than its rows; world 1, at rest, keeps bitwise the contacts it has beside a clean
  world (with the shared buffer the pile's writers, first on the CPU, took world 1's rows), the
  pile keeps exactly its rows, and its overflow is flagged and counted in its world only."""
  sim = load("convex_pile", nworld=2)
  mjm, m = sim.mjm, sim.m
  resting = perturbed_pile_qpos(mjm, 0)[0]
  piled = resting.copy()
  for i in range(6):
    piled[free_qpos_adr(mjm, f"mesh{i}") : free_qpos_adr(mjm, f"mesh{i}") + 3] = (0.0, 0.0, 0.3 + 0.01 * i)
  quiet_overflow(m)

  def run(options, first, naconmax=None):
    collider = sf.install(mjm, m, options)
    d = mjw.put_data(mjm, sim.mjd, nworld=2, naconmax=naconmax)
    d.qpos.assign(np.stack([first, resting]).astype(np.float32))
    mjw.kinematics(m, d)
    sf.collision(m, d)
    out = collider.stats(d), d.overflow.numpy().copy(), [sorted_rows(world_contact_fields(d, w)) for w in (0, 1)]
    sf.uninstall(m)
    return out

  with bitwise_repeatable(m):
    _, _, (found, rest) = run(sf.Options(), piled)
    quota = rest["dist"].size  # world 1's contacts fit, world 0's do not
    assert found["dist"].size > quota > 0
    options = sf.Options(contacts_per_world=quota)
    clean_stats, clean_overflow, (_, clean) = run(options, resting, naconmax=2 * quota)
    stats, overflow, (pile, isolated) = run(options, piled, naconmax=2 * quota)
  assert clean_stats["dropped_contacts_per_world"] == [0, 0] and not clean_overflow.any()
  assert stats["dropped_contacts_per_world"] == [found["dist"].size - quota, 0]
  assert stats["dropped_contacts"] == found["dist"].size - quota
  assert overflow[0] & int(OverflowType.NARROWPHASE) and not overflow[1] & int(OverflowType.NARROWPHASE)
  assert pile["dist"].size == quota
  for f in clean:
    assert np.array_equal(isolated[f], clean[f]), f
    assert np.array_equal(isolated[f], rest[f]), f


SENSOR_SCENE = """<mujoco><worldbody><geom name="floor" type="plane" size="1 1 .1"/>
  <body pos="0 0 .09"><freejoint/><geom name="box" type="box" size=".1 .1 .1"/></body>
  <body pos=".5 0 .2"><freejoint/><geom name="ball" type="sphere" size=".1"/></body></worldbody>
  <sensor><distance geom1="box" geom2="floor" cutoff="1"/></sensor></mujoco>"""


@pytest.mark.parametrize("scene", ["terrain", "nonconvex", "sensor"])
def test_contacts_per_world_with_room_keeps_every_contact(scene):
  """With room for every world, the world rows give each world the contacts of the shared buffer,
  from every writer: heightfield and non-convex candidates, MuJoCo Warp's analytic routines, and
  its own narrow phase for a collision sensor's pair, which writes after the world rows."""
  mjm = load_mjmodel(SENSOR_SCENE if scene == "sensor" else scene)
  sim = load(None, nworld=2, mjm=mjm)
  m = sim.m
  qpos = np.tile(settled_state(mjm, 500).qpos, (2, 1))
  qpos[1, 2] -= 0.01  # the worlds differ: the first free body sinks in world 1
  naconmax = 256

  def run(options):
    collider = sf.install(mjm, m, options)
    d = mjw.put_data(mjm, sim.mjd, nworld=2, naconmax=naconmax)
    d.qpos.assign(qpos.astype(np.float32))
    mjw.kinematics(m, d)
    sf.collision(m, d)
    out = collider.stats(d), int(d.nacon.numpy()[0]), [sorted_rows(world_contact_fields(d, w)) for w in (0, 1)]
    sf.uninstall(m)
    return out

  with bitwise_repeatable(m):
    _, nacon, shared = run(sf.Options())
    stats, packed, rows = run(sf.Options(contacts_per_world=naconmax // 4))  # half the rows stay shared
  assert nacon < naconmax and shared[0]["dist"].size > 0 and shared[1]["dist"].size > 0
  assert packed == nacon and stats["dropped_contacts"] == 0
  for w in (0, 1):
    for f in shared[w]:
      assert np.array_equal(rows[w][f], shared[w][f]), (w, f)


def test_contacts_per_world_beyond_naconmax_raises(pile):
  """nworld x contacts_per_world rows must fit in naconmax: one clear error at the first collision."""
  sf.uninstall(pile.m)
  try:
    sf.install(pile.mjm, pile.m, sf.Options(contacts_per_world=10))
    d = mjw.make_data(pile.mjm, nworld=NWORLD, naconmax=10 * NWORLD - 1)
    with pytest.raises(ValueError, match=rf"contacts_per_world = 10 .*{NWORLD} worlds.*naconmax = {10 * NWORLD - 1}"):
      sf.collision(pile.m, d)
  finally:
    sf.uninstall(pile.m)
    sf.install(pile.mjm, pile.m)


def test_contacts_per_world_refuses_sleeping(pile):
  """A sleeping step's second pass appends to the first pass's contacts, which the quota packs:
  install refuses the combination, and so does a collision after sleeping was enabled."""
  mjm = sleep_model(True, 1e-2)
  with pytest.raises(ValueError, match="contacts_per_world does not work with sleeping"):
    sf.install(mjm, mjw.put_model(mjm), sf.Options(contacts_per_world=8))
  sf.uninstall(pile.m)
  saved = pile.m.opt.enableflags
  try:
    sf.install(pile.mjm, pile.m, sf.Options(contacts_per_world=8))
    pile.m.opt.enableflags = saved | int(mjw.EnableBit.SLEEP)
    with pytest.raises(ValueError, match="contacts_per_world does not work with sleeping"):
      sf.collision(pile.m, mjw.make_data(pile.mjm, nworld=NWORLD))
  finally:
    pile.m.opt.enableflags = saved
    sf.uninstall(pile.m)
    sf.install(pile.mjm, pile.m)


# --- 3. overflow ----------------------------------------------------------------------------------

CANARY = {float: 1234.5, int: -777}


def add_canary(owner, name: str, pad: int = 16):
  """Replaces array ``owner.name`` by a view of a longer array whose tail holds a canary value;
  returns (tail check, view). Writes past the end of the view land in the tail."""
  arr = getattr(owner, name)
  value = CANARY[int] if arr.numpy().dtype.kind in "iu" else CANARY[float]
  big = wp.zeros((arr.shape[0] + pad,) + tuple(arr.shape[1:]), dtype=arr.dtype, device=arr.device)
  big.fill_(value)
  view = big[: arr.shape[0]]
  setattr(owner, name, view)

  def intact() -> bool:
    return bool(np.all(big.numpy()[arr.shape[0] :] == value))

  return intact, view


def count_in(text: str, needle: str) -> int:
  return sum(needle in line for line in text.splitlines())


def test_contact_overflow_is_flagged_counted_and_bounded(pile, capfd):
  """naconmax = 6 (the pile has ~3x more per world): mjw.step flags OverflowType.NARROWPHASE the
  way MuJoCo Warp does, prints its warning unless m.opt.warn_overflow clears it, stats counts the
  dropped contacts, nothing is written past naconmax, and the simulation goes on."""
  sim = pile
  m = sim.m
  d = mjw.make_data(sim.mjm, nworld=NWORLD, naconmax=6)
  checks = [add_canary(d.contact, f)[0] for f in ("dist", "pos", "frame", "geom", "worldid", "dim", "efc_address")]
  printed(capfd)
  mjw.step(m, d)
  out = printed(capfd)
  stats = sf.get_collider(m).stats(d)
  nacon = int(d.nacon.numpy()[0])
  assert nacon > d.naconmax and stats["dropped_contacts"] == nacon - d.naconmax
  assert np.all(d.overflow.numpy() & int(OverflowType.NARROWPHASE))
  assert count_in(out, "narrowphase overflow") == 1, out
  assert all(ok() for ok in checks), "a contact was written past naconmax"
  kept = all_contacts(d)
  assert np.all((kept["worldid"] >= 0) & (kept["worldid"] < NWORLD))
  assert np.all((kept["geom"] >= 0) & (kept["geom"] < sim.mjm.ngeom)) and np.all(np.isfinite(kept["dist"]))

  d.overflow.zero_()
  saved = m.opt.warn_overflow
  quiet_overflow(m)
  try:
    for _ in range(3):
      mjw.step(m, d)
  finally:
    m.opt.warn_overflow = saved
  assert count_in(printed(capfd), "overflow") == 0
  assert np.all(d.overflow.numpy() & int(OverflowType.NARROWPHASE))
  assert all(ok() for ok in checks)
  assert np.all(np.isfinite(d.qpos.numpy()))


@pytest.mark.parametrize("broadphase", ["sap", "nxn"])
def test_pair_overflow_through_step_is_flagged_once_and_bounded(capfd, broadphase):
  """max_collision_pairs = 1: each mjw.step prints the plugin's BROADPHASE warning once (none with
  warn_overflow = 0), sets the bit, counts the dropped pairs, and writes no pair past its budget."""
  sim = load("convex_pile", nworld=2)
  m, d = sim.m, sim.d
  collider = sf.install(sim.mjm, m, sf.Options(broadphase=broadphase, max_collision_pairs=1))
  st = collider.state(m, d).broad
  checks = []
  for name in ("slot_pair", "slot_pairid", "pair", "pairid", "pair_worldid"):
    ok, view = add_canary(st, name)
    if hasattr(st.outputs, name):
      setattr(st.outputs, name, view)
    checks.append(ok)
  printed(capfd)
  for _ in range(2):
    mjw.step(m, d)
  out = printed(capfd)
  assert count_in(out, "mjx_supportfield: broadphase overflow") == 2, out
  stats = collider.stats(d)
  assert stats["pairs_per_world"] == [1, 1] and min(stats["dropped_pairs_per_world"]) > 0
  assert np.all(d.overflow.numpy() & int(OverflowType.BROADPHASE))
  assert all(ok() for ok in checks), "a pair was written past max_collision_pairs"
  d.overflow.zero_()
  quiet_overflow(m)
  for _ in range(2):
    mjw.step(m, d)
  assert count_in(printed(capfd), "overflow") == 0
  assert np.all(d.overflow.numpy() & int(OverflowType.BROADPHASE))
  assert all(ok() for ok in checks) and np.all(np.isfinite(d.qpos.numpy()))


@pytest.mark.parametrize("broadphase", ["sap", "nxn"])
def test_explicit_pair_overflow(broadphase):
  """Three explicit <pair>s (all other collisions off) and a budget of one: two are dropped per
  world, counted and flagged; the kept one gets its contact."""
  cube = vertex_attr(cube_verts())
  bodies = "".join(
    f'<body pos="{0.3 * i} 0 .099"><freejoint/><geom name="p{i}" type="mesh" mesh="cube" contype="0" conaffinity="0"/>'
    f'</body><geom name="b{i}" type="mesh" mesh="cube" pos="{0.3 * i} 0 0" contype="0" conaffinity="0"/>'
    for i in range(3)
  )
  pairs = "".join(f'<pair geom1="b{i}" geom2="p{i}"/>' for i in range(3))
  sim = load(f'<mujoco><asset><mesh name="cube" vertex="{cube}"/></asset><worldbody>{bodies}</worldbody>'
             f"<contact>{pairs}</contact></mujoco>", nworld=2)
  collider = sf.install(sim.mjm, sim.m, sf.Options(broadphase=broadphase, max_collision_pairs=1))
  quiet_overflow(sim.m)
  sf.collision(sim.m, sim.d)
  stats = collider.stats(sim.d)
  assert stats["pairs_per_world"] == [1, 1] and stats["dropped_pairs_per_world"] == [2, 2]
  assert np.all(sim.d.overflow.numpy() & int(OverflowType.BROADPHASE))
  for w in range(2):
    assert len({tuple(g) for g in contacts(sim.d, w).geom}) == 1


# --- 4. determinism -------------------------------------------------------------------------------


def record_run(m, d, nstep: int) -> list:
  """Per step: (all contact fields, qpos)."""
  out = []
  for _ in range(nstep):
    mjw.step(m, d)
    out.append((all_contacts(d), d.qpos.numpy().copy()))
  return out


def world_contacts(rec: dict, w: int) -> dict:
  sel = rec["worldid"] == w
  return {k: v[sel] for k, v in rec.items()}


@pytest.mark.cpu_only(
  reason="MuJoCo Warp's step is not bitwise repeatable on a GPU, even with DeterminismType.ALL: fed the "
  "same contacts, two fresh Data differ in qpos after one step. The plugin's contacts on a GPU are "
  "checked by test_graph_capture_deterministic_contacts, which feeds states instead of stepping."
)
def test_run_after_run_and_fresh_data_are_bitwise_equal(pile):
  """Two fresh Data, and one Data again after mjw.reset_data (warm start and SAP order forgotten),
  give bitwise the same contacts in the same order and the same qpos, step by step."""
  sim = pile
  m = sim.m
  d = mjw.make_data(sim.mjm, nworld=NWORLD)
  first = record_run(m, d, 4)
  second = record_run(m, mjw.make_data(sim.mjm, nworld=NWORLD), 4)
  mjw.reset_data(m, d)
  again = record_run(m, d, 4)
  for k in range(4):
    assert same_arrays(first[k][0], second[k][0]) and np.array_equal(first[k][1], second[k][1]), f"fresh, step {k}"
    assert same_arrays(first[k][0], again[k][0]) and np.array_equal(first[k][1], again[k][1]), f"reset, step {k}"
  # per-world reset, bool and integer masks: that world repeats its run, the others go on
  for w, mask in ((1, wp.array([False, True, False], dtype=bool)), (2, wp.array([0, 0, 1], dtype=int))):
    d, ref = mjw.make_data(sim.mjm, nworld=NWORLD), mjw.make_data(sim.mjm, nworld=NWORLD)
    record_run(m, d, 2)
    record_run(m, ref, 2)
    mjw.reset_data(m, d, mask)
    rerun, tail = record_run(m, d, 4), record_run(m, ref, 4)
    for k in range(4):
      assert same_arrays(world_contacts(rerun[k][0], w), world_contacts(first[k][0], w)), f"world {w}, step {k}"
      assert np.array_equal(rerun[k][1][w], first[k][1][w])
      for other in set(range(NWORLD)) - {w}:
        assert np.array_equal(rerun[k][1][other], tail[k][1][other]), f"world {other} after resetting {w}"


def sort_key(rec: dict, ngeom: int) -> np.ndarray:
  g = rec["geom"].astype(np.int64) + 1
  return (rec["worldid"].astype(np.int64) * (ngeom + 1) + g[:, 0]) * (ngeom + 1) + g[:, 1]


def stable_sorted(rec: dict, ngeom: int) -> dict:
  order = np.argsort(sort_key(rec, ngeom), kind="stable")
  return {k: v[order] for k, v in rec.items()}


def perturbed_pile_qpos(mjm, seed: int) -> np.ndarray:
  rng = np.random.default_rng(seed)
  q = np.tile(mjm.qpos0, (NWORLD, 1))
  for w in range(NWORLD):
    for body in ("mesh4", "mesh5"):  # drop the two falling hulls onto the cluster
      adr = free_qpos_adr(mjm, body)
      q[w, adr : adr + 3] += rng.uniform(-0.01, 0.01, 3) - [0, 0, 0.03]
  return q


def test_deterministic_contacts_are_sorted(pile):
  """m.opt.deterministic & CONTACTS (MuJoCo Warp's switch): contacts come out stably sorted by
  (world, geom1, geom2), every field moved along (the same records as unsorted), and any arrival
  order of the writers (atomics on a GPU) sorts to bitwise the same buffer."""
  sim = pile
  m, ngeom = sim.m, sim.mjm.ngeom
  d_plain, d_sorted = mjw.make_data(sim.mjm, nworld=NWORLD), mjw.make_data(sim.mjm, nworld=NWORLD)
  for d in (d_plain, d_sorted):  # fresh Data: the same (empty) warm-start history
    d.qpos.assign(perturbed_pile_qpos(sim.mjm, 5))
    mjw.kinematics(m, d)
  sf.collision(m, d_plain)
  plain = all_contacts(d_plain)
  saved = m.opt.deterministic
  m.opt.deterministic = DeterminismType.CONTACTS
  try:
    sf.collision(m, d_sorted)
  finally:
    m.opt.deterministic = saved
  got = all_contacts(d_sorted)
  keys = sort_key(got, ngeom)
  assert len(keys) > 2 * NWORLD and np.all(np.diff(keys) >= 0)
  assert not np.all(np.diff(sort_key(plain, ngeom)) >= 0), "unsorted output already sorted: weak test"
  assert same_arrays(got, stable_sorted(plain, ngeom))

  # a GPU's arrival order: writers interleave at random, each keeping its own contacts in order
  rng = np.random.default_rng(0)
  st = sf.get_collider(m).state(m, d_sorted)
  for _ in range(3):
    order = interleave(keys, rng)
    for f, v in got.items():
      arr = getattr(d_sorted.contact, f)
      full = arr.numpy()
      full[: len(keys)] = v[order]
      arr.assign(full)
    contact_sort.sort_contacts(d_sorted, st.sort, ngeom)
    assert same_arrays(all_contacts(d_sorted), got)


def interleave(keys: np.ndarray, rng) -> np.ndarray:
  """A random order of the indices in which equal keys keep their relative order."""
  order = rng.permutation(len(keys))
  out = order.copy()
  for k in np.unique(keys):
    slots = np.sort(np.nonzero(keys[order] == k)[0])
    out[slots] = np.nonzero(keys == k)[0]
  return out


@pytest.mark.parametrize("contacts_per_world", [0, 64])
def test_graph_capture_deterministic_contacts(contacts_per_world):
  """With all of MuJoCo Warp's determinism bits: the same states in give bitwise the same
  contacts, in the same order, uncaptured and replayed from a graph (a CUDA graph on a GPU,
  Warp's CPU graph otherwise), and again after a reset, ten times over; with the shared buffer
  and with rows per world (room for all: which contacts a world past its rows keeps is not
  deterministic on a GPU).

  The states are fed in rather than stepped to: MuJoCo Warp's own step is not bitwise
  repeatable on a GPU (benchmarks/determinism.py measured qpos 1e-7 apart after one step on an
  H200, stock and plugin alike), so trajectories part ways for reasons outside the plugin."""
  nworld = 64 if on_gpu() else 4
  with wp.ScopedDevice(wp.get_device()):
    sim = load("convex_pile", nworld=nworld)
    m = sim.m
    sf.install(sim.mjm, m, sf.Options(contacts_per_world=contacts_per_world))
    m.opt.deterministic = DeterminismType.ALL
    naconmax = nworld * contacts_per_world if contacts_per_world else None
    d_traj, d_ref, d_cap = (mjw.make_data(sim.mjm, nworld=nworld, naconmax=naconmax) for _ in range(3))
    states = []
    for _ in range(5):
      mjw.step(m, d_traj)
      states.append((d_traj.qpos.numpy().copy(), d_traj.qvel.numpy().copy()))
    mjw.fwd_position(m, d_ref)  # loads every kernel and makes the per-Data state before capturing
    mjw.fwd_position(m, d_cap)
    with wp.ScopedCapture() as capture:
      mjw.fwd_position(m, d_cap)
    runs = []
    for _ in range(10):
      mjw.reset_data(m, d_ref)  # forgets the warm-start history: both Data start alike
      mjw.reset_data(m, d_cap)
      run = []
      for qpos, qvel in states:
        for d in (d_ref, d_cap):
          d.qpos.assign(qpos)
          d.qvel.assign(qvel)
        mjw.fwd_position(m, d_ref)
        wp.capture_launch(capture.graph)
        wp.synchronize()
        ref, cap = all_contacts(d_ref), all_contacts(d_cap)
        assert len(ref["dist"]) > 0 and same_arrays(ref, cap)
        assert not d_cap.overflow.numpy().any()
        run.append(cap)
      runs.append(run)
    assert all(same_arrays(a, b) for run in runs[1:] for a, b in zip(runs[0], run))
    sf.uninstall(m)


# --- 5. sleeping ----------------------------------------------------------------------------------

SLEEP_SCENE = """<mujoco><option timestep="0.002" sleep_tolerance="{tol}">{flag}</option>
  <asset><mesh name="cube" vertex="{cube}"/></asset><worldbody><geom name="floor" type="plane" size="2 2 .1"/>
  <body name="a" pos="0 0 .0495"><freejoint/><geom name="a" type="mesh" mesh="cube"/></body>
  <body name="b" pos="0 0 .17"><freejoint/><geom name="b" type="mesh" mesh="cube"/></body>
  <body name="c" pos="1 0 .0495"><freejoint/><geom name="c" type="mesh" mesh="cube"/></body>
  </worldbody></mujoco>"""


def sleep_model(sleep: bool, tol: float) -> mujoco.MjModel:
  flag = '<flag sleep="enable"/>' if sleep else ""
  return mujoco.MjModel.from_xml_string(SLEEP_SCENE.format(tol=tol, flag=flag, cube=vertex_attr(cube_verts())))


def pair_set(geoms) -> set:
  return {tuple(sorted(int(x) for x in g)) for g in geoms}


@pytest.mark.parametrize("broadphase", ["sap", "nxn"])
def test_sleeping_matches_mujoco_c(broadphase):
  """Cubes a and c rest on the floor and fall asleep; cube b drops onto a and wakes it. Step by
  step, the awake bodies and the touching geom pairs are MuJoCo C's: sleeping bodies keep still
  without floor contacts, a woken body gets its contacts in the step it wakes, c sleeps on."""
  mjm = sleep_model(True, 1e-2)
  m = mjw.put_model(mjm)
  d = mjw.make_data(mjm)
  sf.install(mjm, m, sf.Options(broadphase=broadphase))
  mjd = mujoco.MjData(mjm)
  a, c = mjm.body("a").id, mjm.body("c").id
  adr_c = free_qpos_adr(mjm, "c")
  floor, ga, gb = (geom_name_id(mjm, n) for n in ("floor", "a", "b"))
  events = {"a asleep": None, "a woken": None}
  qc = None
  for step in range(60):
    mjw.step(m, d)
    mujoco.mj_step(mjm, mjd)
    awake = d.body_awake.numpy()[0]
    pairs = pair_set(contacts(d, 0).geom)
    assert awake.tolist() == mjd.body_awake.tolist(), f"step {step}"
    assert pairs == pair_set((k.geom1, k.geom2) for k in mjd.contact[: mjd.ncon]), f"step {step}"
    if not awake[a] and events["a asleep"] is None:
      events["a asleep"] = step
    if events["a asleep"] is not None and awake[a] and events["a woken"] is None:
      events["a woken"] = step
      assert {(floor, ga), (ga, gb)} <= pairs  # both of a's contacts in the step it wakes
    if not awake[c]:
      qc = d.qpos.numpy()[0].copy() if qc is None else qc
      assert np.array_equal(d.qpos.numpy()[0][adr_c : adr_c + 7], qc[adr_c : adr_c + 7]), "a sleeping body moved"
  assert events["a asleep"] is not None and events["a woken"] is not None, events
  assert not d.body_awake.numpy()[0][c]


def test_sleep_enabled_but_never_asleep_matches_disabled():
  """sleep_tolerance 1e-12: nothing falls asleep in 30 steps, and contacts and motion follow the
  run with sleeping disabled (MuJoCo Warp's own two runs differ by ~1e-17 m, so not bitwise)."""
  runs = []
  for sleep in (True, False):
    mjm = sleep_model(sleep, 1e-12)
    m = mjw.put_model(mjm)
    d = mjw.make_data(mjm)
    sf.install(mjm, m)
    runs.append(record_run(m, d, 30))
    assert np.all(d.body_awake.numpy()[0][1:] == 1)
  for k, ((c1, q1), (c2, q2)) in enumerate(zip(*runs)):
    assert np.array_equal(c1["geom"], c2["geom"]), f"step {k}"
    np.testing.assert_allclose(c1["dist"], c2["dist"], atol=1e-7, err_msg=f"step {k}")
    np.testing.assert_allclose(c1["frame"], c2["frame"], atol=1e-5, err_msg=f"step {k}")
    np.testing.assert_allclose(q1, q2, atol=1e-7, err_msg=f"step {k}")
