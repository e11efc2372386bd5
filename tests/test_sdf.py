"""SDF fallback: baked hull SDFs against closed forms, the disk cache, the trigger, and the
contact of a small cube deep inside a large one."""

import numpy as np
import pytest
import warp as wp
from conftest import load

import mujoco
import mjx_supportfield as sf
from mjx_supportfield.geometry import sdf as sdfmod
from mjx_supportfield.types import SUPPORT_REFINED
from mjx_supportfield.types import MeshSupport

_SDF = sdfmod.sdf_funcs(SUPPORT_REFINED)

# the test kernels are only run forward: no adjoint code to build (on CUDA it would take minutes)
wp.set_module_options({"enable_backward": False})

CUBE = " ".join(str(x) for x in (np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)])).ravel())
XML = f"""
<mujoco>
  <asset>
    <mesh name="big" vertex="{CUBE}" scale=".1 .1 .1"/>
    <mesh name="small" vertex="{CUBE}" scale=".01 .01 .01"/>
  </asset>
  <worldbody>
    <body><freejoint/><geom name="big" type="mesh" mesh="big"/></body>
    <body pos="0.06 0.03 0"><freejoint/><geom name="small" type="mesh" mesh="small"/></body>
  </worldbody>
</mujoco>
"""


@pytest.fixture(scope="module")
def sim():
  s = load(XML)
  collider = sf.install(s.mjm, s.m)
  return s, collider


@wp.kernel
def _values(sdf: sdfmod.MeshSdf, mesh: int, pts: wp.array(dtype=wp.vec3), out: wp.array(dtype=float)):
  i = wp.tid()
  out[i] = sdfmod.mesh_sdf_value(sdf, mesh, pts[i])


def test_baked_sdf_matches_box_distance(sim):
  s, collider = sim
  big = mujoco.mj_name2id(s.mjm, mujoco.mjtObj.mjOBJ_MESH, "big")
  pts = np.random.default_rng(0).uniform(-0.11, 0.11, size=(2000, 3)).astype(np.float32)
  out = wp.zeros(len(pts), dtype=float)
  wp.launch(_values, dim=len(pts), inputs=[collider.mesh_sdf, big, wp.array(pts, dtype=wp.vec3), out])
  q = np.abs(pts) - 0.1
  exact = np.linalg.norm(np.maximum(q, 0), axis=1) + np.minimum(q.max(axis=1), 0)
  cell = 0.2 * 1.4 / 32
  # trilinear interpolation of a distance field: exact on faces' interiors, off by < a cell near edges
  assert np.abs(out.numpy() - exact).max() < cell
  assert np.median(np.abs(out.numpy() - exact)) < 0.05 * cell


def test_disk_cache(sim, tmp_path, monkeypatch):
  s, _ = sim
  monkeypatch.setenv("MJX_SUPPORTFIELD_CACHE", str(tmp_path))
  big = mujoco.mj_name2id(s.mjm, mujoco.mjtObj.mjOBJ_MESH, "big")
  first = sdfmod.build_mesh_sdf(s.mjm, 16, {big})
  assert len(list((tmp_path / "sdf").iterdir())) == 1
  second = sdfmod.build_mesh_sdf(s.mjm, 16, {big})
  np.testing.assert_array_equal(first.values.numpy(), second.values.numpy())


@wp.kernel
def _trigger(depth: wp.array(dtype=float), out: wp.array(dtype=int)):
  i = wp.tid()
  out[i] = int(sdfmod.needs_sdf(depth[i], 0.1, 0.02, 0.5))


def test_trigger_is_the_overlap_ratio():
  depth = np.array([0.0, 0.0199, 0.0201, 0.5], np.float32)  # threshold 0.5 x 2 x 0.02 = 0.02
  out = wp.zeros(len(depth), dtype=int)
  wp.launch(_trigger, dim=len(depth), inputs=[wp.array(depth, dtype=float), out])
  np.testing.assert_array_equal(out.numpy(), [0, 0, 1, 1])


@wp.kernel
def _contact(ms: MeshSupport, sdf: sdfmod.MeshSdf, a: sf.types.Shape, b: sf.types.Shape, out: wp.array(dtype=wp.vec4)):
  c = _SDF.sdf_contact(a, b, ms, sdf, 1.0e-4)
  out[0] = wp.vec4(c.depth, c.normal[0], c.normal[1], c.normal[2])


def _shape(s, name):
  g = mujoco.mj_name2id(s.mjm, mujoco.mjtObj.mjOBJ_GEOM, name)
  sh = sf.types.Shape()
  sh.gtype = int(s.mjm.geom_type[g])
  sh.pos = wp.vec3(*s.d.geom_xpos.numpy()[0, g])
  sh.rot = wp.mat33(*s.d.geom_xmat.numpy()[0, g].ravel())
  sh.size = wp.vec3(*s.mjm.geom_size[g])
  sh.mesh = int(s.mjm.geom_dataid[g])
  sh.center = sh.pos
  sh.inflate = 0.0
  return sh


def test_small_cube_deep_inside_large_one(sim):
  """The nearest way out of the big cube is +x: 0.1 - (0.06 - 0.01) = 0.05 deep."""
  s, collider = sim
  out = wp.zeros(1, dtype=wp.vec4)
  wp.launch(_contact, dim=1, inputs=[collider.mesh_support, collider.mesh_sdf, _shape(s, "big"), _shape(s, "small"), out])
  depth, *normal = out.numpy()[0]
  assert depth == pytest.approx(0.05, abs=2e-3)
  assert normal == pytest.approx([1.0, 0.0, 0.0], abs=2e-2)
  # and through the pipeline the pair gets that answer (MPR and the fallback agree here)
  sf.collision(s.m, s.d)
  n = int(s.d.nacon.numpy()[0])
  assert n >= 1
  assert -s.d.contact.dist.numpy()[:n].max() == pytest.approx(0.05, abs=2e-3)
