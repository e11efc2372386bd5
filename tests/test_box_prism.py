"""box_prism.py: whether a box and a heightfield triangle's prism are apart by the margin band,
by the box's axes and the edge pairs' cross products, against MuJoCo C's own GJK/EPA
(mj_geomDistance) on the same two shapes, the prism given to C as a six-vertex mesh.

Random triangles and box poses, from apart to a few centimetres deep: a pair the axes part must
be at least the band apart by C's distance (the test only drops work GJK/EPA would find nothing
in), and most pairs apart that the prism's own faces do not part are parted. The same axes with
the prism's faces give the exact penetration (box_prism_contact), which C's depth matches, and
the heightfield stage takes it where a box prism's GJK/EPA answer cannot be right.
"""

import mujoco
import numpy as np
import warp as wp

from mjx_supportfield.geometry.box_prism import box_axes_part
from mjx_supportfield.geometry.box_prism import box_prism_contact
from mjx_supportfield.stages.hfield_cells import Heightfield
from mjx_supportfield.stages.hfield_cells import cell_corners
from mjx_supportfield.stages.hfield_cells import cell_size
from mjx_supportfield.stages.hfield_window import TerrainPair
from mjx_supportfield.stages.hfield_window import _box_prism_answer
from mjx_supportfield.stages.hfield_window import _scale
from mjx_supportfield.types import Shape

BAND = 0.002
BOTTOM = -0.05
BOX = wp.constant(int(mujoco.mjtGeom.mjGEOM_BOX))


@wp.func
def _box(pos: wp.vec3, rot: wp.mat33, half: wp.vec3) -> Shape:
  box = Shape()
  box.gtype = BOX
  box.pos = pos
  box.rot = rot
  box.size = half
  box.mesh = -1
  box.center = pos
  box.inflate = 0.0
  return box


@wp.kernel(module="unique", enable_backward=False)
def _box_axes_part(top: wp.array2d(dtype=wp.vec3), pos: wp.array(dtype=wp.vec3), rot: wp.array(dtype=wp.mat33),
                   half: wp.vec3, band: float, part_out: wp.array(dtype=int)):
  i = wp.tid()
  box = _box(pos[i], rot[i], half)
  part_out[i] = wp.where(box_axes_part(top[i, 0], top[i, 1], top[i, 2], BOTTOM, box, band), 1, 0)


def _cases(n, seed=3):
  rng = np.random.default_rng(seed)
  top = np.zeros((n, 3, 3))
  top[:, :, :2] = [[0.0, 0.0], [0.05, 0.0], [0.05, 0.05]]
  top[:, :, 2] = rng.uniform(0.0, 0.02, (n, 3))
  pos = np.column_stack([rng.uniform(-0.03, 0.08, n), rng.uniform(-0.03, 0.08, n), rng.uniform(0.0, 0.05, n)])
  quat = rng.normal(size=(n, 4))
  quat /= np.linalg.norm(quat, axis=1, keepdims=True)
  rot = np.zeros((n, 9))
  for i in range(n):
    mujoco.mju_quat2Mat(rot[i], quat[i])
  return top, pos, rot.reshape(n, 3, 3)


def _faces_part(top, pos, rot, half):
  """Whether the prism's top plane or a side wall parts them by the band (the stage's own tests)."""
  corners = pos + np.array([[sx, sy, sz] for sz in (-1, 1) for sy in (-1, 1) for sx in (-1, 1)]) * half @ rot.T
  n = np.cross(top[1] - top[0], top[2] - top[0])
  n /= np.linalg.norm(n)
  if (corners @ n).min() - top[0] @ n >= BAND:
    return True
  for i in range(3):
    e = top[(i + 1) % 3] - top[i]
    out = np.array([e[1], -e[0], 0.0])
    out = -out if out @ (top[(i + 2) % 3] - top[i]) > 0 else out
    out /= np.linalg.norm(out)
    if (corners @ out).min() - top[i] @ out >= BAND:
      return True
  return False


def _distance(top, pos, rot, half):
  """MuJoCo C's signed distance between the prism and the box (capped at the band)."""
  verts = np.vstack([top, np.column_stack([top[:, :2], np.full(3, BOTTOM)])])
  xml = f"""<mujoco><asset><mesh name="prism" vertex="{' '.join(map(str, verts.ravel()))}"/></asset>
    <worldbody><geom name="prism" type="mesh" mesh="prism"/>
    <body pos="{' '.join(map(str, pos))}" xyaxes="{' '.join(map(str, np.concatenate([rot[:, 0], rot[:, 1]])))}">
    <freejoint/><geom type="box" size="{' '.join(map(str, half))}"/></body></worldbody></mujoco>"""
  m = mujoco.MjModel.from_xml_string(xml)
  d = mujoco.MjData(m)
  mujoco.mj_forward(m, d)
  return mujoco.mj_geomDistance(m, d, 0, 1, 2 * BAND, None)


def test_parted_pairs_are_apart_by_mujocos_distance():
  n, half = 600, (0.02, 0.015, 0.004)
  top, pos, rot = _cases(n)
  with wp.ScopedDevice("cpu"):
    part = wp.zeros(n, dtype=int)
    wp.launch(_box_axes_part, dim=n, inputs=[wp.array(top, dtype=wp.vec3), wp.array(pos, dtype=wp.vec3),
                                             wp.array(rot, dtype=wp.mat33), wp.vec3(*half), BAND], outputs=[part])
    part = part.numpy()
  left = parted = 0
  for i in range(n):
    dist = _distance(top[i], pos[i], rot[i], half)
    if part[i]:
      assert dist >= BAND - 1e-6, (i, dist)
    if dist >= BAND and not _faces_part(top[i], pos[i], rot[i], half):
      left += 1
      parted += int(part[i])
  assert left > 20 and parted > 0.5 * left, (parted, left)


@wp.kernel(module="unique", enable_backward=False)
def _box_prism_contact(top: wp.array2d(dtype=wp.vec3), pos: wp.array(dtype=wp.vec3), rot: wp.array(dtype=wp.mat33),
                       half: wp.vec3, point_out: wp.array(dtype=wp.vec4), normal_out: wp.array(dtype=wp.vec3)):
  i = wp.tid()
  box = _box(pos[i], rot[i], half)
  point, normal = box_prism_contact(top[i, 0], top[i, 1], top[i, 2], BOTTOM, box, 1.0e-6)
  point_out[i] = point
  normal_out[i] = normal


def _overlap(top, corners, n):
  """The overlap of the prism and the box's corners along unit direction(s) n (rows)."""
  verts = np.vstack([top, np.column_stack([top[:, :2], np.full(3, BOTTOM)])])
  return (verts @ n.T).max(axis=0) - (corners @ n.T).min(axis=0)


def test_penetration_is_the_least_overlap_and_mujocos_depth():
  """The exact penetration: along its normal the two overlap by its depth, along no direction
  by less (a dense sample of directions), and MuJoCo C's GJK/EPA (mj_geomDistance) gives the
  same depth, or less where its EPA stopped short, never more. The point lies in both shapes
  grown by the depth."""
  n, half = 400, (0.02, 0.015, 0.004)
  top, pos, rot = _cases(n, seed=5)
  with wp.ScopedDevice("cpu"):
    point = wp.zeros(n, dtype=wp.vec4)
    normal = wp.zeros(n, dtype=wp.vec3)
    wp.launch(_box_prism_contact, dim=n, inputs=[wp.array(top, dtype=wp.vec3), wp.array(pos, dtype=wp.vec3),
                                                 wp.array(rot, dtype=wp.mat33), wp.vec3(*half)],
              outputs=[point, normal])
    point, normal = point.numpy().astype(float), normal.numpy().astype(float)
  rng = np.random.default_rng(0)
  directions = rng.normal(size=(20000, 3))
  directions /= np.linalg.norm(directions, axis=1, keepdims=True)
  signs = np.array([[sx, sy, sz] for sz in (-1, 1) for sy in (-1, 1) for sx in (-1, 1)])
  deep = same = 0
  for i in range(n):
    depth = point[i, 3]
    if depth <= 1.0e-4:
      continue
    deep += 1
    corners = pos[i] + signs * half @ rot[i].T
    assert abs(_overlap(top[i], corners, normal[i][None])[0] - depth) < 1.0e-6, i
    assert _overlap(top[i], corners, directions).min() >= depth - 1.0e-6, i
    c_depth = -_distance(top[i], pos[i], rot[i], half)
    assert c_depth <= depth + 1.0e-5, (i, c_depth, depth)
    same += int(abs(c_depth - depth) < 1.0e-5)
    local = rot[i].T @ (point[i, :3] - pos[i])
    assert np.all(np.abs(local) <= np.array(half) + depth + 1.0e-6), i
    assert point[i, 2] >= BOTTOM - depth - 1.0e-6, i
  assert deep > 50 and same > 0.9 * deep, (same, deep)


@wp.kernel(module="unique", enable_backward=False)
def _stage_answer(data: wp.array(dtype=float), size: wp.vec4, pos: wp.vec3, rot: wp.mat33, half: wp.vec3,
                  answers: wp.array(dtype=wp.vec4), normals: wp.array(dtype=wp.vec3), band: float,
                  answer_out: wp.array(dtype=wp.vec4), normal_out: wp.array(dtype=wp.vec3)):
  i = wp.tid()
  hfield = Heightfield()
  hfield.data = data
  hfield.adr = 0
  hfield.nrow = 2
  hfield.ncol = 2
  hfield.size = size
  box = _box(pos, rot, half)
  tp = TerrainPair()
  tp.band = band
  tp.lo = pos - wp.vec3(0.05)
  tp.hi = pos + wp.vec3(0.05)
  dx, dy = cell_size(hfield)
  p00, p01, p10, p11, na, nb = cell_corners(hfield, dx, dy, 0, 0)
  answer, normal = _box_prism_answer(hfield, box, tp, 0, p00, p01, p10, p11, _scale(tp, dx, dy), answers[i], normals[i])
  answer_out[i] = answer
  normal_out[i] = normal


def test_the_stage_takes_the_exact_answer_where_gjk_epas_cannot_be_right():
  """A box prism's GJK/EPA answer (depth with the band) stands unless it cannot be right: none
  while the two penetrate, deeper than the exact penetration, or a normal into the terrain
  (float32 EPA's failures on a face resting on a prism); an answer only short of the exact depth
  stands too (MuJoCo C's EPA stops short on the same prisms)."""
  size = wp.vec4(0.05, 0.05, 0.02, 0.05)  # one cell 0.1 m wide, elevations up to 2 cm
  data = wp.array([0.1, 0.6, 0.3, 0.9], dtype=float, device="cpu")
  half = (0.03, 0.02, 0.01)
  rot = np.eye(3)
  pos = np.array([-0.02, 0.02, 0.014])  # over the first triangle, its lowest face into the slope
  band = 0.001
  top = np.array([[-0.05, -0.05, 0.002], [-0.05, 0.05, 0.006], [0.05, 0.05, 0.018]])
  signs = np.array([[sx, sy, sz] for sz in (-1, 1) for sy in (-1, 1) for sx in (-1, 1)])
  corners = pos + signs * np.array(half)
  exact = -_distance(top, pos, rot, half)  # MuJoCo C's depth (the exact one, as the test above checks)
  assert exact > 1.0e-3
  up = np.cross(top[1] - top[0], top[2] - top[0])
  up = up / np.linalg.norm(up) * np.sign(up[2])
  point = [-0.03, 0.0, 0.005]
  cases = [  # (answer, normal, stands)
    ((*point, band + exact), up, True),  # right, along the triangle's normal
    ((*point, band + 0.5 * exact), up, True),  # short: kept
    ((0.0, 0.0, 0.0, 0.0), (0.0, 0.0, 0.0), False),  # none
    ((*point, band + 2.0 * exact), (0.0, 0.0, 1.0), False),  # deeper than the penetration
    ((*point, band + 0.5 * exact), (0.0, 0.0, -1.0), False),  # into the terrain
  ]
  with wp.ScopedDevice("cpu"):
    answers = wp.array([c[0] for c in cases], dtype=wp.vec4)
    normals = wp.array([c[1] for c in cases], dtype=wp.vec3)
    out = wp.zeros(len(cases), dtype=wp.vec4)
    nout = wp.zeros(len(cases), dtype=wp.vec3)
    wp.launch(_stage_answer, dim=len(cases), inputs=[data, size, wp.vec3(*pos), wp.mat33(*rot.ravel()),
                                                     wp.vec3(*half), answers, normals, band], outputs=[out, nout])
    out, nout = out.numpy(), nout.numpy()
  for i, (answer, normal, stands) in enumerate(cases):
    if stands:
      np.testing.assert_allclose(out[i], answer, atol=1.0e-7)
      np.testing.assert_allclose(nout[i], normal, atol=1.0e-7)
    else:
      assert abs(out[i, 3] - band - exact) < 2.0e-5, (i, out[i])
      assert abs(_overlap(top, corners, nout[i][None].astype(float))[0] - exact) < 2.0e-5, i
