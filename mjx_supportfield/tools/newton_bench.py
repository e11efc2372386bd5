"""Newton's collision pipeline timed on MuJoCo Warp's poses: a third column for ``bench``.

Optional: needs the ``newton`` extra (``pip install mjx-supportfield[newton]``); nothing in the
package imports this module unless asked (``bench --newton``, ``run_suite.py --newton``).

Newton imports the same MJCF (``ModelBuilder.add_mjcf``), its meshes become convex hulls with no
vertex cap (``approximate_meshes("convex_hull")``, ``mesh_maxhullvert=0``; MuJoCo collides the
hull of every mesh), its contact gap is zero (``rigid_gap = 0``; MuJoCo's default gap is 0 too),
and its candidate pairs are made MuJoCo's: the pairs Newton would test that MuJoCo filters out
(same weld, parent/child, contype/conaffinity, ``<exclude>``, no dofs) become Newton filter pairs,
Newton filter pairs that drop a pair MuJoCo tests are taken out, and the ``explicit`` broad phase
gets MuJoCo's pair list itself. Each world's bodies are placed
where MuJoCo Warp's step put them (``xpos``/``xquat`` of the body of the same name), so Newton
collides the very poses that stock MuJoCo Warp and the plugin collide.
"""

import dataclasses
import time
from typing import Callable, Optional

import mujoco
import mujoco_warp as mjw
import numpy as np
import warp as wp

wp.set_module_options({"enable_backward": False})

INSTALL_HINT = "pip install mjx-supportfield[newton]"
BROAD_PHASES = ("nxn", "sap", "explicit")
# poses (MuJoCo Warp steps) per captured graph, as bench's collision-in-steps timing
STEPS_PER_GRAPH = 10
# a shape is where MuJoCo has its geom when they agree within this (m, plus this much of its size)
POSE_TOL = 1e-4


def import_newton():
  """Imports Newton, or raises ImportError naming the extra that installs it."""
  try:
    import newton
  except ImportError as e:
    raise ImportError(f"the Newton column needs Newton 1.8: {INSTALL_HINT} ({e})") from None
  return newton


@dataclasses.dataclass
class NewtonResult:
  """Newton's collision pipeline on one scene and world count.

  ``ms``: the best broad phase's milliseconds per collision inside the evolving poses;
  ``ms_by_broadphase`` / ``frozen_ms_by_broadphase``: each broad phase inside the evolving poses /
  repeated on the settled state; ``contacts_per_world``: the best broad phase's, at the settled
  state; ``poses``: how Newton's bodies got MuJoCo's poses; ``notes``: every way the setup differs
  from MuJoCo's (unmatched geoms, pairs Newton cannot test, overflow).
  """

  scene: str
  nworld: int
  ms: Optional[float]
  broadphase: Optional[str]
  frozen_ms: Optional[float]
  ms_by_broadphase: dict
  frozen_ms_by_broadphase: dict
  contacts_per_world: Optional[float]
  contacts_by_broadphase: dict
  poses: str
  pairs_per_world: int
  notes: list


@dataclasses.dataclass
class NewtonWorld:
  """One world of the scene in Newton, matched to MuJoCo: ``body_of[i]`` is the MuJoCo body of
  Newton body i, ``geom_of[s]`` the MuJoCo geom of Newton shape s (-1: none or not colliding),
  ``pairs`` MuJoCo's candidate pairs as Newton shape pairs (i < j)."""

  builder: object
  body_of: np.ndarray
  geom_of: np.ndarray
  pairs: np.ndarray
  notes: list


def _tail_matches(label: str, name: str) -> bool:
  return bool(name) and (label == name or label.endswith("/" + name))


def _map_bodies(builder, mjm) -> np.ndarray:
  """MuJoCo body of each Newton body: by order (both walk the body tree depth first) where the
  counts agree and every named body matches, else by name."""
  names = [mujoco.mj_id2name(mjm, mujoco.mjtObj.mjOBJ_BODY, b) or "" for b in range(mjm.nbody)]
  labels = list(builder.body_label)
  if len(labels) == mjm.nbody - 1 and all(not names[i + 1] or _tail_matches(lab, names[i + 1]) for i, lab in enumerate(labels)):
    return np.arange(1, mjm.nbody, dtype=np.int32)
  body_of = np.full(len(labels), -1, dtype=np.int32)
  for i, lab in enumerate(labels):
    hits = [b for b in range(1, mjm.nbody) if _tail_matches(lab, names[b])]
    if len(hits) == 1:
      body_of[i] = hits[0]
  return body_of


def _colliding_geoms(mjm) -> np.ndarray:
  colliding = (mjm.geom_contype | mjm.geom_conaffinity) != 0
  colliding[mjm.pair_geom1] = True
  colliding[mjm.pair_geom2] = True
  return colliding


def _colliding_shapes(builder, collide_flag: int) -> list[int]:
  """Newton shapes that collide with shapes: the flag set and a collision group (group 0 is how
  the import marks MuJoCo's contype = conaffinity = 0)."""
  return [s for s, f in enumerate(builder.shape_flags) if f & collide_flag and builder.shape_collision_group[s] != 0]


def _map_shapes(builder, mjm, body_of, collide_flag) -> np.ndarray:
  """MuJoCo geom of each colliding Newton shape: by name within the same body, then the unnamed
  ones in order within the body."""
  shape_body = np.asarray(builder.shape_body)
  colliding = _colliding_geoms(mjm)
  geom_of = np.full(len(shape_body), -1, dtype=np.int32)
  for nb in np.unique(shape_body):
    mb = 0 if nb < 0 else int(body_of[nb])
    if mb < 0:
      continue
    shapes = [s for s in _colliding_shapes(builder, collide_flag) if shape_body[s] == nb]
    left = list(np.nonzero((mjm.geom_bodyid == mb) & colliding)[0])
    for s in shapes:
      label = builder.shape_label[s]
      hit = [g for g in left if _tail_matches(label, mujoco.mj_id2name(mjm, mujoco.mjtObj.mjOBJ_GEOM, g) or "")]
      if len(hit) == 1:
        geom_of[s] = hit[0]
        left.remove(hit[0])
    unnamed = [g for g in left if not mujoco.mj_id2name(mjm, mujoco.mjtObj.mjOBJ_GEOM, g)]
    for s in shapes:
      if geom_of[s] < 0 and unnamed:
        geom_of[s] = unnamed.pop(0)
  return geom_of


def _mujoco_pairs(mjm, geom_of) -> tuple[np.ndarray, int]:
  """MuJoCo's contact candidate pairs as Newton shape pairs; and how many have a geom no Newton
  shape stands for."""
  m = mjw.put_model(mjm)
  contact = m.nxn_pairid_filtered.numpy().reshape(-1, 2)[:, 0] > -2
  geom_pairs = m.nxn_geom_pair_filtered.numpy().reshape(-1, 2)[contact]
  shape_of = np.full(mjm.ngeom, -1, dtype=np.int64)
  shape_of[geom_of[geom_of >= 0]] = np.nonzero(geom_of >= 0)[0]
  pairs = shape_of[geom_pairs]
  ok = (pairs >= 0).all(axis=1)
  pairs = np.sort(pairs[ok], axis=1)
  return pairs[np.lexsort((pairs[:, 1], pairs[:, 0]))], int((~ok).sum())


def _newton_pairs(builder, collide_flag) -> np.ndarray:
  """The shape pairs Newton's nxn and sap broad phases would test in one world (before boxes):
  collision groups, same body, static-static and the filter pairs, as Newton filters them."""
  shapes = np.array(_colliding_shapes(builder, collide_flag), dtype=np.int64)
  i, j = np.triu_indices(len(shapes), k=1)
  a, b = shapes[i], shapes[j]
  group = np.asarray(builder.shape_collision_group)
  body = np.asarray(builder.shape_body)
  ga, gb = group[a], group[b]
  groups_ok = (ga != 0) & (gb != 0) & np.where(ga > 0, (ga == gb) | (gb < 0), ga != gb)
  keep = groups_ok & ~((body[a] >= 0) & (body[a] == body[b])) & ~((body[a] < 0) & (body[b] < 0))
  pairs = np.stack((a[keep], b[keep]), axis=1)
  filtered = {tuple(sorted(p)) for p in builder.shape_collision_filter_pairs}
  if filtered:
    pairs = np.array([p for p in pairs.tolist() if tuple(p) not in filtered], dtype=np.int64).reshape(-1, 2)
  return pairs


def build_world(path: str, mjm: Optional[mujoco.MjModel] = None) -> NewtonWorld:
  """One world of ``path`` in Newton with MuJoCo's settings (module docstring), matched to MuJoCo."""
  newton = import_newton()
  mjm = mjm or mujoco.MjModel.from_xml_path(path)
  builder = newton.ModelBuilder()
  builder.rigid_gap = 0.0
  builder.add_mjcf(path, mesh_maxhullvert=0)
  builder.approximate_meshes("convex_hull")
  collide_flag = int(newton.ShapeFlags.COLLIDE_SHAPES)
  notes = []
  body_of = _map_bodies(builder, mjm)
  if (body_of < 0).any():
    notes.append(f"{int((body_of < 0).sum())} of {len(body_of)} Newton bodies have no MuJoCo body of their name")
  geom_of = _map_shapes(builder, mjm, body_of, collide_flag)
  colliding = _colliding_shapes(builder, collide_flag)
  unmatched = [s for s in colliding if geom_of[s] < 0]
  if unmatched:
    notes.append(f"{len(unmatched)} colliding Newton shapes match no MuJoCo geom, e.g. {builder.shape_label[unmatched[0]]}")
  nmissing_geoms = int(_colliding_geoms(mjm).sum()) - (len(colliding) - len(unmatched))
  if nmissing_geoms > 0:
    notes.append(f"{nmissing_geoms} colliding MuJoCo geoms have no Newton shape")
  pairs, nunmapped = _mujoco_pairs(mjm, geom_of)
  if nunmapped:
    notes.append(f"{nunmapped} MuJoCo pairs have a geom without a Newton shape")
  mj_set = set(map(tuple, pairs.tolist()))
  # pairs MuJoCo tests that a Newton filter pair drops: Newton filters parent and child even where
  # the parent is welded to the world, which MuJoCo does not
  builder.shape_collision_filter_pairs = [p for p in builder.shape_collision_filter_pairs
                                          if tuple(sorted(map(int, p))) not in mj_set]
  nt_set = set(map(tuple, _newton_pairs(builder, collide_flag).tolist()))
  for a, b in sorted(nt_set - mj_set):  # MuJoCo filters them (weld, parent, masks, exclude, no dofs)
    builder.add_shape_collision_filter_pair(int(a), int(b))
  missing = mj_set - nt_set
  if missing:
    notes.append(f"{len(missing)} of MuJoCo's {len(mj_set)} pairs a world are filtered by Newton's collision "
                 "groups: nxn and sap skip them, explicit tests them")
  return NewtonWorld(builder, body_of, geom_of, pairs, notes)


def _quat_xyzw(q_wxyz: np.ndarray) -> np.ndarray:
  return np.concatenate([q_wxyz[..., 1:], q_wxyz[..., :1]], axis=-1)


def _rotate(q_xyzw: np.ndarray, v: np.ndarray) -> np.ndarray:
  """Rotates points v (n x 3) by the unit quaternion q (x, y, z, w)."""
  u, w = np.asarray(q_xyzw[:3], dtype=np.float64), float(q_xyzw[3])
  return v + 2.0 * np.cross(u, np.cross(u, v) + w * v)


def mujoco_body_poses(world: NewtonWorld, mjd: mujoco.MjData) -> np.ndarray:
  """Each Newton body's pose (x, y, z, qx, qy, qz, qw) from the MuJoCo body of its name."""
  mb = np.maximum(world.body_of, 0)
  return np.concatenate([mjd.xpos[mb], _quat_xyzw(mjd.xquat[mb])], axis=1)


def pose_mismatches(world: NewtonWorld, mjm: mujoco.MjModel, mjd: mujoco.MjData,
                    body_poses: Optional[np.ndarray] = None) -> list[str]:
  """Shapes that are not where MuJoCo has their geom when Newton's bodies take ``body_poses``
  (default: MuJoCo's body poses, ``mujoco_body_poses``): primitives by centre, boxes and convex
  meshes by world bounding box (the hull's box is the mesh's), planes by normal and offset.
  Empty when the poses are exact."""
  newton = import_newton()
  gt = newton.GeoType
  b = world.builder
  if body_poses is None:
    body_poses = mujoco_body_poses(world, mjd)
  bad = []
  for s, g in enumerate(world.geom_of):
    if g < 0:
      continue
    nb = b.shape_body[s]
    if nb >= 0:
      body_p, body_q = body_poses[nb, :3].astype(np.float64), body_poses[nb, 3:].astype(np.float64)
    else:
      body_p, body_q = np.zeros(3), np.array([0.0, 0.0, 0.0, 1.0])
    xf = b.shape_transform[s]
    local_p, local_q = np.array(xf.p, dtype=np.float64), np.array(xf.q, dtype=np.float64)
    p = body_p + _rotate(body_q, local_p[None])[0]

    def world_pts(v):
      return p + _rotate(body_q, _rotate(local_q, v))

    gp, gmat = mjd.geom_xpos[g], mjd.geom_xmat[g].reshape(3, 3)
    kind = b.shape_type[s]
    scale = np.array(b.shape_scale[s], dtype=np.float64)
    if kind == gt.PLANE:
      n_newton = world_pts(np.array([[0.0, 0.0, 1.0]]))[0] - p
      ok = np.allclose(n_newton, gmat[:, 2], atol=POSE_TOL) and abs(n_newton @ (p - gp)) < POSE_TOL
    elif kind in (gt.BOX, gt.CONVEX_MESH, gt.MESH):
      if kind == gt.BOX:
        corners = np.array(np.meshgrid([-1, 1], [-1, 1], [-1, 1])).reshape(3, -1).T
        ours, theirs = corners * scale, corners * mjm.geom_size[g]
      else:
        ours = np.asarray(b.shape_source[s].vertices, dtype=np.float64) * scale
        mesh = mjm.geom_dataid[g]
        adr, num = mjm.mesh_vertadr[mesh], mjm.mesh_vertnum[mesh]
        theirs = mjm.mesh_vert[adr:adr + num].astype(np.float64)
      ours = world_pts(ours)
      theirs = gp + theirs @ gmat.T
      size = float(np.ptp(theirs, axis=0).max())
      tol = POSE_TOL * (1.0 + size)
      ok = np.allclose(ours.min(0), theirs.min(0), atol=tol) and np.allclose(ours.max(0), theirs.max(0), atol=tol)
    else:  # spheres, capsules, cylinders, ellipsoids, heightfields: the centre
      ok = np.allclose(p, gp, atol=POSE_TOL * (1.0 + float(np.max(mjm.geom_rbound[g]))))
    if not ok:
      bad.append(b.shape_label[s])
  return bad


@wp.kernel
def _place_bodies(xpos: wp.array2d(dtype=wp.vec3), xquat: wp.array2d(dtype=wp.quat), body_world: wp.array(dtype=int),
                  mj_body: wp.array(dtype=int), body_q: wp.array(dtype=wp.transform)):
  i = wp.tid()
  world, b = body_world[i], mj_body[i]
  q = xquat[world, b]  # MuJoCo Warp keeps MuJoCo's (w, x, y, z); Warp's transform wants (x, y, z, w)
  body_q[i] = wp.transform(xpos[world, b], wp.quat(q[1], q[2], q[3], q[0]))


@wp.kernel
def _gather_joint_q(qpos: wp.array2d(dtype=float), coord_world: wp.array(dtype=int), coord_src: wp.array(dtype=int),
                    joint_q: wp.array(dtype=float)):
  i = wp.tid()
  joint_q[i] = qpos[coord_world[i], coord_src[i]]


def joint_coordinate_map(builder, mjm: mujoco.MjModel) -> Optional[np.ndarray]:
  """For each joint coordinate of one Newton world, its MuJoCo qpos address (quaternions turned
  from (w, x, y, z) to (x, y, z, w)); None where the joints do not pair up. Newton's joints other
  than fixed ones pair in order with MuJoCo's (both walk the body tree depth first)."""
  newton = import_newton()
  jt, mt = newton.JointType, mujoco.mjtJoint
  kinds = {jt.FREE: (mt.mjJNT_FREE, [0, 1, 2, 4, 5, 6, 3]), jt.BALL: (mt.mjJNT_BALL, [1, 2, 3, 0]),
           jt.REVOLUTE: (mt.mjJNT_HINGE, [0]), jt.PRISMATIC: (mt.mjJNT_SLIDE, [0])}
  src = np.full(builder.joint_coord_count, -1, dtype=np.int32)
  mj_joint = 0
  for j, kind in enumerate(builder.joint_type):
    if kind == jt.FIXED:
      continue
    if kind not in kinds or mj_joint >= mjm.njnt or mjm.jnt_type[mj_joint] != kinds[kind][0]:
      return None
    start = builder.joint_q_start[j]
    order = kinds[kind][1]
    src[start:start + len(order)] = mjm.jnt_qposadr[mj_joint] + np.array(order)
    mj_joint += 1
  if mj_joint != mjm.njnt or (src < 0).any():
    return None
  return src


def newton_fk_poses(world: NewtonWorld, mjm: mujoco.MjModel, mjd: mujoco.MjData) -> Optional[np.ndarray]:
  """Newton's own forward kinematics of MuJoCo's qpos (one world): each body's pose, or None when
  the joints do not pair up."""
  newton = import_newton()
  src = joint_coordinate_map(world.builder, mjm)
  if src is None:
    return None
  model = world.builder.finalize(device="cpu")
  state = model.state()
  joint_q = wp.array(mjd.qpos[src].astype(np.float32), dtype=float, device="cpu")
  newton.eval_fk(model, joint_q, model.joint_qd, state)
  return state.body_q.numpy()


class _Poser:
  """Puts poses from MuJoCo Warp (``evolving_poses`` entries) on the bodies of every Newton world:
  the body poses of the MuJoCo bodies of their names, or (``fk``) Newton's forward kinematics of
  MuJoCo's qpos."""

  def __init__(self, world: NewtonWorld, mjm: mujoco.MjModel, model, state, nworld: int, fk: bool):
    self.model, self.state, self.fk = model, state, fk
    self.nbody = len(world.body_of)
    self.body_world = wp.array(np.repeat(np.arange(nworld), self.nbody).astype(np.int32), dtype=int)
    self.mj_body = wp.array(np.tile(np.maximum(world.body_of, 0), nworld).astype(np.int32), dtype=int)
    if fk:
      src = joint_coordinate_map(world.builder, mjm)
      ncoord = len(src)
      if model.joint_coord_count != nworld * ncoord:
        raise RuntimeError("Newton's replicated joint coordinates are not one block a world")
      self.coord_world = wp.array(np.repeat(np.arange(nworld), ncoord).astype(np.int32), dtype=int)
      self.coord_src = wp.array(np.tile(src, nworld).astype(np.int32), dtype=int)
      self.joint_q = wp.zeros(nworld * ncoord, dtype=float)

  def __call__(self, pose):
    """Launches the kernels that pose every world (capturable)."""
    if not self.nbody:
      return
    if self.fk:
      wp.launch(_gather_joint_q, dim=self.joint_q.shape[0], inputs=[pose[2], self.coord_world, self.coord_src, self.joint_q])
      import_newton().eval_fk(self.model, self.joint_q, self.model.joint_qd, self.state)
    else:
      wp.launch(_place_bodies, dim=self.body_world.shape[0],
                inputs=[pose[0], pose[1], self.body_world, self.mj_body, self.state.body_q])

  def check(self, want: np.ndarray) -> None:
    """Raises unless world 0's bodies hold ``want`` (x, y, z, qx, qy, qz, qw per body)."""
    got = self.state.body_q.numpy()[:self.nbody]
    if not np.allclose(got, want, atol=1e-4):
      raise RuntimeError("Newton's bodies do not hold the poses meant for them (quaternion order?)")


def _choose_poses(world: NewtonWorld, mjm: mujoco.MjModel, mjd: mujoco.MjData) -> tuple[bool, np.ndarray, str]:
  """Whether to pose Newton by its own FK of MuJoCo's qpos instead of MuJoCo's body poses (only
  when the body poses put some shape elsewhere and the FK puts fewer there), world 0's expected
  body poses, and a line saying which and how exact."""
  body_poses = mujoco_body_poses(world, mjd)
  bad = pose_mismatches(world, mjm, mjd, body_poses)
  if not bad:
    return False, body_poses, "MuJoCo's body poses (exact: every shape where MuJoCo has its geom)"
  fk_poses = newton_fk_poses(world, mjm, mjd)
  fk_bad = None if fk_poses is None else pose_mismatches(world, mjm, mjd, fk_poses)
  why = f"MuJoCo's body poses put {len(bad)} shapes elsewhere (e.g. {bad[0]})"
  if fk_bad is not None and len(fk_bad) < len(bad):
    exact = "exact" if not fk_bad else f"INEXACT for {len(fk_bad)} shapes (e.g. {fk_bad[0]})"
    return True, fk_poses, f"Newton's FK of MuJoCo's qpos ({exact}): {why}"
  fk_why = "its joints do not pair up with MuJoCo's" if fk_poses is None else f"it puts {len(fk_bad)} shapes elsewhere"
  return False, body_poses, f"MuJoCo's body poses, INEXACT: {why}; not Newton's FK: {fk_why}"


def _time_calls(prepare: Callable[[int], None], call: Callable[[], None], ncalls: int, launches: int) -> tuple[float, str]:
  """Milliseconds per ``call``, each after ``prepare(k)``: on a GPU CUDA events around every call
  inside a captured graph of ``ncalls`` calls, replayed until ``launches`` calls (prepare untimed);
  on the CPU the wall time of each call. Also how it was timed."""
  device = wp.get_device()
  if not device.is_cuda:
    total = 0.0
    for k in range(ncalls):
      prepare(k)
      wp.synchronize()
      t = time.perf_counter()
      call()
      wp.synchronize()
      total += time.perf_counter() - t
    return total / ncalls * 1e3, "wall time (CPU)"

  def record():
    events = []
    for k in range(ncalls):
      prepare(k)
      start, end = wp.Event(enable_timing=True), wp.Event(enable_timing=True)
      wp.record_event(start)
      call()
      wp.record_event(end)
      events.append((start, end))
    return events

  from mjx_supportfield.tools.bench import replay_events

  try:
    with wp.ScopedCapture() as capture:
      events = record()
  except Exception as e:  # a pipeline that cannot be captured is still timed, by events alone
    wp.synchronize()
    how = f"events, not graph-captured ({type(e).__name__}: {e})"
    record()  # warm
    total, replays = 0.0, max(1, launches // ncalls)
    for _ in range(replays):
      events = record()
      wp.synchronize()
      total += sum(wp.get_event_elapsed_time(s, e) for s, e in events)
    return total / (replays * ncalls), how
  return replay_events(capture.graph, events, launches), "events in a CUDA graph"


def evolving_poses(mjm: mujoco.MjModel, mjd: mujoco.MjData, nworld: int, nsteps: int,
                   nconmax: Optional[int] = None) -> list[tuple[wp.array, wp.array, wp.array]]:
  """(xpos, xquat, qpos) of every world in MuJoCo Warp's Data of ``mjd``, then after each of ``nsteps``
  stock MuJoCo Warp steps from it: the settled state and the poses that bench's
  collision-in-steps timing collides."""
  ncon = nconmax or int(1.5 * mjd.ncon) + 16
  m = mjw.put_model(mjm)
  d = mjw.put_data(mjm, mjd, nworld=nworld, nconmax=ncon, njmax=6 * ncon + mjd.nefc)
  poses = [(wp.clone(d.xpos), wp.clone(d.xquat), wp.clone(d.qpos))]
  for _ in range(nsteps):
    mjw.step(m, d)
    poses.append((wp.clone(d.xpos), wp.clone(d.xquat), wp.clone(d.qpos)))
  wp.synchronize()
  return poses


def replicate(world: NewtonWorld, nworld: int):
  """The Newton model of ``nworld`` copies of ``world``, and each body's world and MuJoCo body."""
  newton = import_newton()
  scene = newton.ModelBuilder()
  scene.rigid_gap = 0.0
  scene.replicate(world.builder, nworld)
  model = scene.finalize()
  nbody = len(world.body_of)
  body_world = model.body_world.numpy()
  if nbody and not (body_world == np.repeat(np.arange(nworld), nbody)).all():
    raise RuntimeError("Newton's replicated bodies are not in world order; cannot place them")
  shape_world = model.shape_world.numpy()
  nshape = len(world.geom_of)
  if not (shape_world == np.repeat(np.arange(nworld), nshape)).all():
    raise RuntimeError("Newton's replicated shapes are not in world order; cannot list the explicit pairs")
  return model


def _explicit_pairs(world: NewtonWorld, nworld: int) -> np.ndarray:
  """MuJoCo's pairs of every world, in the replicated model's shape indices."""
  nshape = len(world.geom_of)
  return (world.pairs[None] + (np.arange(nworld) * nshape)[:, None, None]).reshape(-1, 2).astype(np.int32)


def _time_broad_phase(model, state, mode: str, explicit: np.ndarray, contact_max: int, place: "_Poser", settled,
                      steps: list, launches: int) -> tuple[float, float, float, str]:
  """One broad phase: contacts per world at the settled state, ms per collide repeated there
  (frozen) and inside the evolving poses, and a note (overflow, not graph-captured) or "". The
  pipeline is freed on return, before the next one is allocated."""
  newton = import_newton()
  nworld = model.world_count
  if mode == "explicit":
    kwargs = {"shape_pairs_filtered": wp.array(explicit, dtype=wp.vec2i)}
  else:  # nxn and sap emit at most MuJoCo's pairs (the rest are filter pairs); Newton's default is n(n-1)/2
    kwargs = {"shape_pairs_max": max(1, len(explicit))}
  pipeline = newton.CollisionPipeline(model, broad_phase=mode, verify_buffers=False, rigid_contact_max=contact_max,
                                      **kwargs)
  out = pipeline.contacts()
  place(settled)
  pipeline.collide(state, out)  # compiles outside the timing
  wp.synchronize()
  count = int(out.rigid_contact_count.numpy()[0])
  notes = [f"the contact buffer ({contact_max}) overflowed"] if count >= contact_max else []

  def collide():
    pipeline.collide(state, out)

  frozen, _ = _time_calls(lambda k: None, collide, STEPS_PER_GRAPH, launches)
  ms, how = _time_calls(lambda k: place(steps[k]), collide, STEPS_PER_GRAPH, launches)
  if how.startswith("events, not"):
    notes.append(how)
  return min(count, contact_max) / nworld, frozen, ms, "; ".join(notes)


def bench_newton(path: str, nworlds: list[int], launches: int, settle_steps: int, nconmax: Optional[int] = None,
                 broad_phases=BROAD_PHASES, mjd: Optional[mujoco.MjData] = None,
                 keyframe: Optional[int] = None) -> list[NewtonResult]:
  """Times Newton's CollisionPipeline on ``path`` for each nworld and broad phase: inside the
  poses of evolving stock MuJoCo Warp steps from the settled state (bench.settled_state, from
  keyframe ``keyframe`` if given), and repeated on the settled state (frozen). See the module
  docstring for the settings."""
  import_newton()  # the error naming the extra before anything else
  from mjx_supportfield.tools.bench import scene_name  # bench imports this module lazily: no cycle at import
  from mjx_supportfield.tools.bench import settled_state

  mjm = mujoco.MjModel.from_xml_path(path)
  mjd = mjd or settled_state(mjm, settle_steps, keyframe)
  world = build_world(path, mjm)
  fk, want, poses_how = _choose_poses(world, mjm, mjd)
  # contacts a world: 4x the room bench gives MuJoCo Warp (Newton's own estimate sizes for every
  # pair touching, gigabytes at 8192 worlds); an overflow is named in the notes
  contact_room = 4 * (nconmax or int(1.5 * mjd.ncon) + 16)
  results = []
  for nworld in nworlds:
    model = replicate(world, nworld)
    state = model.state()
    place = _Poser(world, mjm, model, state, nworld, fk)
    settled, *steps = evolving_poses(mjm, mjd, nworld, STEPS_PER_GRAPH, nconmax)
    place(settled)
    place.check(want)
    explicit = _explicit_pairs(world, nworld)
    ms, frozen, contacts, notes = {}, {}, {}, list(world.notes)
    for mode in broad_phases:
      contacts[mode], frozen[mode], ms[mode], note = _time_broad_phase(model, state, mode, explicit, nworld * contact_room,
                                                                      place, settled, steps, launches)
      notes += [f"{mode}: {note}"] if note else []
    best = min(ms, key=ms.get) if ms else None
    results.append(NewtonResult(scene_name(path), nworld, ms.get(best), best, frozen.get(best), ms, frozen,
                                contacts.get(best), contacts, poses_how, len(world.pairs), notes))
  return results


def settled_contact_pairs(path: str, settle_steps: int, broad_phase: str = "nxn", nworld: int = 2) -> tuple[set, float]:
  """The MuJoCo geom pairs of Newton's contacts in world 0 at the settled state (as bench_newton
  sets it up) and its contacts per world: for checking Newton's contacts against MuJoCo C's."""
  newton = import_newton()
  from mjx_supportfield.tools.bench import settled_state

  mjm = mujoco.MjModel.from_xml_path(path)
  mjd = settled_state(mjm, settle_steps)
  world = build_world(path, mjm)
  model = replicate(world, nworld)
  state = model.state()
  fk, want, _ = _choose_poses(world, mjm, mjd)
  place = _Poser(world, mjm, model, state, nworld, fk)
  place(evolving_poses(mjm, mjd, nworld, 0)[0])
  place.check(want)
  kwargs = {"shape_pairs_filtered": wp.array(_explicit_pairs(world, nworld), dtype=wp.vec2i)} if broad_phase == "explicit" else {}
  pipeline = newton.CollisionPipeline(model, broad_phase=broad_phase, **kwargs)
  contacts = pipeline.contacts()
  pipeline.collide(state, contacts)
  n = int(contacts.rigid_contact_count.numpy()[0])
  shape0, shape1 = contacts.rigid_contact_shape0.numpy()[:n], contacts.rigid_contact_shape1.numpy()[:n]
  nshape = len(world.geom_of)
  in_world0 = (shape0 < nshape) & (shape1 < nshape)
  pairs = {tuple(sorted((int(world.geom_of[a]), int(world.geom_of[b])))) for a, b in zip(shape0[in_world0], shape1[in_world0])}
  return pairs, n / nworld


def json_extra(results: list[NewtonResult]) -> dict:
  """The ``newton`` key of a bench results file: one entry per scene and world count, with the
  Newton version."""
  import importlib.metadata as md

  return {"newton": [dataclasses.asdict(r) for r in results], "newton_version": md.version("newton")}


def format_newton(results: list[NewtonResult], rows: Optional[list] = None) -> str:
  """Newton beside stock and the plugin: collision ms inside the evolving steps (frozen state in
  brackets), Newton's best broad phase and each mode's time, contacts per world."""
  by_key = {(r.scene, r.nworld, r.impl): r for r in rows or [] if r.stage == "collision"}
  out = [f"{'scene':24s} {'nworld':>6s} {'stock ms':>16s} {'plugin ms':>16s} {'newton ms':>16s} {'best':8s} "
         f"{'nxn / sap / explicit (in steps)':32s} {'con/world stock':>15s} {'plugin':>7s} {'newton':>7s}"]

  def cell(ms, frozen):
    if ms is None:
      return f"{'-':>16s}"
    return f"{ms:7.3f} ({frozen:6.3f})" if frozen is not None else f"{ms:16.3f}"

  for n in results:
    s, p = by_key.get((n.scene, n.nworld, "stock")), by_key.get((n.scene, n.nworld, "plugin"))
    modes = " / ".join(f"{n.ms_by_broadphase[m]:.3f}" if m in n.ms_by_broadphase else "-" for m in BROAD_PHASES)
    out.append(f"{n.scene:24s} {n.nworld:6d} {cell(s.ms if s else None, getattr(s, 'frozen_ms', None))} "
               f"{cell(p.ms if p else None, getattr(p, 'frozen_ms', None))} {cell(n.ms, n.frozen_ms)} "
               f"{n.broadphase or '-':8s} {modes:32s} {s.contacts_per_world if s else float('nan'):15.1f} "
               f"{p.contacts_per_world if p else float('nan'):7.1f} {n.contacts_per_world or 0.0:7.1f}")
    for note in [n.poses] + n.notes:
      out.append(f"  {n.scene}: {note}")
  return "\n".join(out)
