"""box_prism.py: whether a box and a heightfield triangle's prism are apart by the margin band,
by the box's axes and the edge pairs' cross products, against MuJoCo C's own GJK/EPA
(mj_geomDistance) on the same two shapes, the prism given to C as a six-vertex mesh.

Random triangles and box poses, from apart to a few centimetres deep: a pair the axes part must
be at least the band apart by C's distance (the test only drops work GJK/EPA would find nothing
in), and most pairs apart that the prism's own faces do not part are parted.
"""

import mujoco
import numpy as np
import warp as wp

from mjx_supportfield.geometry.box_prism import box_axes_part
from mjx_supportfield.types import Shape

BAND = 0.002
BOTTOM = -0.05
BOX = wp.constant(int(mujoco.mjtGeom.mjGEOM_BOX))


@wp.kernel(module="unique", enable_backward=False)
def _box_axes_part(top: wp.array2d(dtype=wp.vec3), pos: wp.array(dtype=wp.vec3), rot: wp.array(dtype=wp.mat33),
                   half: wp.vec3, band: float, part_out: wp.array(dtype=int)):
  i = wp.tid()
  box = Shape()
  box.gtype = BOX
  box.pos = pos[i]
  box.rot = rot[i]
  box.size = half
  box.mesh = -1
  box.center = pos[i]
  box.inflate = 0.0
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
