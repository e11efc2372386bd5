"""candidates.py: merging contact candidates in place and choosing the ones written.

The heightfield, closed-form and non-convex kernels hold a pair's candidates in one struct that
their functions change by reference; these tests run the functions in a small kernel and check
what each keeps, merges, replaces and picks.
"""

import numpy as np
import warp as wp

from mjx_supportfield.geometry.mpr import MprResult
from mjx_supportfield.stages.candidates import NCANDIDATE
from mjx_supportfield.stages.candidates import TAG_DEEPEST
from mjx_supportfield.stages.candidates import TAG_PRISM
from mjx_supportfield.stages.candidates import TAG_VERTEX
from mjx_supportfield.stages.candidates import add_tagged
from mjx_supportfield.stages.candidates import choose
from mjx_supportfield.stages.candidates import depth_at
from mjx_supportfield.stages.candidates import empty_with_room
from mjx_supportfield.stages.candidates import normal_at
from mjx_supportfield.stages.candidates import pos_at
from mjx_supportfield.stages.hfield_cells import prism_answer_kept


@wp.kernel(module="unique", enable_backward=False)
def _merge_and_choose(
  pos_in: wp.array(dtype=wp.vec3),
  depth_in: wp.array(dtype=float),
  tag_in: wp.array(dtype=int),
  room: int,
  spacing: float,
  max_contacts: int,
  keep: float,
  n_out: wp.array(dtype=int),
  pos_out: wp.array(dtype=wp.vec3),
  normal_out: wp.array(dtype=wp.vec3),
  depth_out: wp.array(dtype=float),
  order_out: wp.array(dtype=int),
):
  cands = empty_with_room(room)
  for i in range(pos_in.shape[0]):
    # each candidate's normal names it, so that the test sees which one a slot holds
    add_tagged(cands, pos_in[i], wp.vec3(float(i), 0.0, 1.0), depth_in[i], spacing, tag_in[i])
  cands.keep = keep
  n_out[0] = cands.n
  for k in range(cands.n):
    pos_out[k] = pos_at(cands, k)
    normal_out[k] = normal_at(cands, k)
    depth_out[k] = depth_at(cands, k)
  order = choose(cands, max_contacts)
  for k in range(NCANDIDATE):
    order_out[k] = order[k]


def _tag(triangle, source):
  """Candidates.tag of a candidate of terrain triangle ``triangle`` (candidates.triangle_tag)."""
  return 4 * triangle + 1 + source


def _run(pos, depth, room=NCANDIDATE, spacing=0.01, max_contacts=4, keep=1.0e10, tags=None):
  tags = np.zeros(len(pos), dtype=np.int32) if tags is None else np.asarray(tags, dtype=np.int32)
  with wp.ScopedDevice("cpu"):
    n = wp.zeros(1, dtype=int)
    p, nrm = wp.zeros(NCANDIDATE, dtype=wp.vec3), wp.zeros(NCANDIDATE, dtype=wp.vec3)
    d, order = wp.zeros(NCANDIDATE, dtype=float), wp.zeros(NCANDIDATE, dtype=int)
    wp.launch(_merge_and_choose, dim=1,
              inputs=[wp.array(np.asarray(pos, dtype=np.float32), dtype=wp.vec3),
                      wp.array(np.asarray(depth, dtype=np.float32), dtype=float), wp.array(tags, dtype=int), room,
                      spacing, max_contacts, keep],
              outputs=[n, p, nrm, d, order])
    count = int(n.numpy()[0])
    return (count, p.numpy()[:count], nrm.numpy()[:count, 0].astype(int), d.numpy()[:count],
            [k for k in order.numpy() if k >= 0])


def test_near_candidates_merge_into_the_deeper():
  count, pos, source, depth, _ = _run([[0, 0, 0], [0.005, 0, 0], [0.1, 0, 0], [0.004, 0, 0]],
                                      [0.01, 0.02, 0.03, 0.015])
  assert count == 2
  # the second replaced the first in its slot (deeper, within spacing); the fourth was shallower
  np.testing.assert_allclose(pos[0], [0.005, 0, 0], atol=1e-7)
  assert source.tolist() == [1, 2]
  np.testing.assert_allclose(depth, [0.02, 0.03], atol=1e-7)


def test_a_full_list_gives_up_its_shallowest():
  pos = [[0.1 * i, 0, 0] for i in range(5)]
  count, _, source, depth, _ = _run(pos, [0.05, 0.01, 0.04, 0.03, 0.02], room=3)
  assert count == 3
  # 0.03 replaced 0.01 (slot 1), then 0.02 was shallower than all three kept
  assert source.tolist() == [0, 3, 2]
  np.testing.assert_allclose(depth, [0.05, 0.03, 0.04], atol=1e-7)


def test_choice_starts_deepest_then_spreads():
  pos = [[0, 0, 0], [0.01, 0, 0], [1.0, 0, 0], [0.5, 0, 0]]
  _, _, _, _, order = _run(pos, [0.01, 0.05, 0.02, 0.03], spacing=0.001, max_contacts=2)
  assert order == [1, 2]  # the deepest, then the one farthest from it
  _, _, _, _, order = _run(pos, [0.01, 0.05, 0.02, 0.03], spacing=0.001, max_contacts=2, keep=0.015)
  assert sorted(order[2:]) == [3]  # beyond max_contacts only those deeper than keep


def test_a_triangle_gives_one_contact_its_prisms_where_there_is_one():
  # triangle 7: a corner and the deepest point deeper than its prism's answer; triangle 9: two
  # corners and no prism answer; an untagged candidate between them
  pos = [[0, 0, 0], [0.1, 0, 0], [0.2, 0, 0], [1.0, 0, 0], [1.1, 0, 0], [0.5, 0, 0]]
  depth = [0.05, 0.04, 0.01, 0.03, 0.02, 0.001]
  tags = [_tag(7, TAG_VERTEX), _tag(7, TAG_DEEPEST), _tag(7, TAG_PRISM), _tag(9, TAG_VERTEX), _tag(9, TAG_VERTEX), 0]
  _, _, _, _, order = _run(pos, depth, spacing=0.001, max_contacts=5, tags=tags)
  assert sorted(order) == [2, 3, 5]  # triangle 7's prism answer, triangle 9's deeper corner, the untagged
  _, _, _, _, order = _run(pos, depth, spacing=0.001, max_contacts=1, keep=0.0, tags=tags)
  assert sorted(order) == [2, 3, 5]  # beyond max_contacts by the same rule


@wp.kernel(module="unique", enable_backward=False)
def _answer_kept(cand_pos: wp.array(dtype=wp.vec3), cand_normal: wp.array(dtype=wp.vec3),
                 cand_depth: wp.array(dtype=float), answer: wp.array(dtype=wp.vec4),
                 normal: wp.array(dtype=wp.vec3), face: wp.vec3, one_per_prism: int,
                 kept_out: wp.array(dtype=int)):
  i = wp.tid()
  c = empty_with_room(NCANDIDATE)
  for k in range(cand_pos.shape[0]):
    add_tagged(c, cand_pos[k], cand_normal[k], cand_depth[k], 1.0e-4, 0)
  res = MprResult()
  res.hit = 1
  res.pos = wp.vec3(answer[i][0], answer[i][1], answer[i][2])
  res.depth = answer[i][3]
  res.normal = normal[i]
  kept = prism_answer_kept(c, res, face, wp.vec3(0.0), 0.1, 0.1, 0, 1.0, 1.0e-6, one_per_prism == 1)
  kept_out[i] = wp.where(kept, 1, 0)


def _kept(cands, witnesses, normals, face=(0.0, 0.0, 1.0), one_per_prism=False, depth=0.004):
  """prism_answer_kept of answers depth deep (their witnesses on the terrain, their normals) on
  triangle 0 (x <= y seen along z) of a cell 0.1 m wide with its corner (0, 0) at the origin and
  the triangle's normal ``face``, against candidates (pos, normal, depth)."""
  answers = [(*(np.array(w) - 0.5 * depth * np.array(n)), depth) for w, n in zip(witnesses, normals)]
  with wp.ScopedDevice("cpu"):
    kept = wp.zeros(len(answers), dtype=int)
    wp.launch(_answer_kept, dim=len(answers), inputs=[
      wp.array([c[0] for c in cands], dtype=wp.vec3), wp.array([c[1] for c in cands], dtype=wp.vec3),
      wp.array([c[2] for c in cands], dtype=float), wp.array(answers, dtype=wp.vec4),
      wp.array(normals, dtype=wp.vec3), wp.vec3(*face), int(one_per_prism)], outputs=[kept])
    return kept.numpy().tolist()


def test_a_prism_answer_is_dropped_only_for_a_face_contact_over_its_own_triangle():
  """A prism's answer along its triangle's normal is dropped where a plane-pass candidate over the
  same triangle with that normal is as deep (B's face already rests there); one over a
  neighbouring triangle in the same plane is another place of B's and leaves the answer. Its
  witness must lie on the top face, or below it by no more than float32 rounding of the depth."""
  up = (0.0, 0.0, 1.0)
  over_it = [((0.03, 0.07, 0.002), up, 0.005)]
  beside = [((0.07, 0.02, 0.002), up, 0.005)]  # over the cell's other triangle
  on_top = (0.02, 0.06, 0.0)
  assert _kept(over_it, [on_top], [up]) == [0]
  assert _kept(beside, [on_top], [up]) == [1]
  rounded, under = (0.02, 0.06, -0.005 * 0.004), (0.02, 0.06, -0.05 * 0.004)
  assert _kept(beside, [rounded, under], [up, up]) == [1, 0]


def test_a_box_prism_answer_tilted_across_the_top_edge_stands():
  """GJK/EPA's answer for a box's or a mesh's prism (one a prism, as MuJoCo C's) may tilt more
  than 60 degrees from its steep triangle's normal where it points up by 60 degrees or less (B's
  edge across the triangle's top edge); an MPR answer that tilted, or any answer within 60
  degrees of horizontal, is a side wall's and dropped."""
  far = [((0.5, 0.5, 0.0), (1.0, 0.0, 0.0), 0.0001)]
  face = (0.0, -0.8, 0.6)  # a triangle 53 degrees steep; the witness on its plane through the origin
  witness = (0.02, 0.06, 0.08)
  across = (0.0, 0.5, 0.8660254)  # 84 degrees from the face normal, 30 from vertical
  sideways = (0.0, 0.95, 0.3122499)  # 72 degrees from vertical
  assert _kept(far, [witness, witness], [across, sideways], face, one_per_prism=True) == [1, 0]
  assert _kept(far, [witness, witness], [across, sideways], face, one_per_prism=False) == [0, 0]
