"""Multi-contact pass: the kernels that give the pairs the MPR (or GJK) kernel queued their
other contacts, after the convex narrow phase.

Face pairs first (face_pair_kernel): a pair touching face on feature along its normal is
clipped (manifold_kernel, faceclip.py's device functions); the rest are tilted (tilt_kernel in
closed form, tilt_mpr_kernel by MPR, multicontact.py's device functions) and patch_kernel
writes each tilted pair's contacts. This module owns those kernels (built for one support mode
by ``pass_kernels``) and their stage class, ``MultiContactPass``; their queues are the narrow
phase's per-Data buffers (``narrowphase.Buffers``), as the MPR kernel fills them.
"""

import functools
from types import SimpleNamespace

import warp as wp
from mujoco_warp._src.collision_core import contact_margin_gap
from mujoco_warp._src.math import make_frame

from mjx_supportfield.geometry.faceclip import TILTS
from mjx_supportfield.geometry.faceclip import faceclip_funcs
from mjx_supportfield.geometry.faceclip import manifold_dist
from mjx_supportfield.geometry.faceclip import manifold_pos
from mjx_supportfield.geometry.mpr import MprResult
from mjx_supportfield.geometry.mpr import MprSettings
from mjx_supportfield.geometry.mpr import settings_of
from mjx_supportfield.geometry.multicontact import NPERTURB
from mjx_supportfield.geometry.multicontact import UNKNOWN
from mjx_supportfield.geometry.multicontact import tilt_funcs
from mjx_supportfield.geometry.multicontact import tilt_rotation
from mjx_supportfield.geometry.shapes import posed_pair
from mjx_supportfield.launch.contact_quota import ContactMixing
from mjx_supportfield.launch.contact_quota import ContactQuota
from mjx_supportfield.launch.contact_quota import ContactRows
from mjx_supportfield.launch.contact_quota import contact_mixing
from mjx_supportfield.launch.contact_quota import contact_outputs
from mjx_supportfield.launch.contact_quota import mixed_params
from mjx_supportfield.launch.contact_quota import write_row
from mjx_supportfield.launch.grid import GRID_THREADS
from mjx_supportfield.launch.grid import HEAVY_REGISTERS
from mjx_supportfield.options import Options
from mjx_supportfield.stages.narrowphase import Buffers
from mjx_supportfield.stages.narrowphase import write_pair_contacts
from mjx_supportfield.types import MeshSupport
from mjx_supportfield.types import SupportMode
from mjx_supportfield.types import mode_module
from mjx_supportfield.types import MODULE_OPTIONS

wp.set_module_options(MODULE_OPTIONS)


@wp.func
def _queued_patch(
  geom_type: wp.array(dtype=int),
  geom_dataid: wp.array2d(dtype=int),
  geom_size: wp.array2d(dtype=wp.vec3),
  geom_rbound: wp.array2d(dtype=float),
  geom_xpos_in: wp.array2d(dtype=wp.vec3),
  geom_xmat_in: wp.array2d(dtype=wp.mat33),
  ms: MeshSupport,
  band: float,
  geoms: wp.vec2i,
  worldid: int,
  result: wp.vec4,
  pos: wp.vec3,
):
  """A queued multi-contact pair: its shapes (A grown by the margin band), scale, and the first contact."""
  a, b, scale = posed_pair(geom_type, geom_dataid, geom_size, geom_rbound, geom_xpos_in, geom_xmat_in, ms, band,
                           geoms, worldid)
  res = MprResult()
  res.hit = 1
  res.normal = wp.vec3(result[0], result[1], result[2])
  res.depth = result[3]
  res.pos = pos
  return a, b, scale, res


@wp.func
def _queued_first(result: wp.vec4, pos: wp.vec3) -> MprResult:
  """A queued multi-contact pair's first contact."""
  res = MprResult()
  res.hit = 1
  res.normal = wp.vec3(result[0], result[1], result[2])
  res.depth = result[3]
  res.pos = pos
  return res


@wp.func
def _queued_tilt(
  geom_type: wp.array(dtype=int),
  geom_dataid: wp.array2d(dtype=int),
  geom_size: wp.array2d(dtype=wp.vec3),
  geom_rbound: wp.array2d(dtype=float),
  geom_margin: wp.array2d(dtype=float),
  geom_gap: wp.array2d(dtype=float),
  pair_margin: wp.array2d(dtype=float),
  pair_gap: wp.array2d(dtype=float),
  geom_xpos_in: wp.array2d(dtype=wp.vec3),
  geom_xmat_in: wp.array2d(dtype=wp.mat33),
  ms: MeshSupport,
  mc_perturbation: float,
  pair_in: wp.array(dtype=wp.vec2i),
  pairid_in: wp.array(dtype=wp.vec2i),
  pair_worldid_in: wp.array(dtype=int),
  patch_pair: wp.array(dtype=int),
  patch_result: wp.array(dtype=wp.vec4),
  patch_pos: wp.array(dtype=wp.vec3),
  i: int,
  j: int,
):
  """Attempt j // NPERTURB of tilt j % NPERTURB of queued multi-contact pair i: its shapes,
  scale, first contact and rotation."""
  cid = patch_pair[i]
  geoms = pair_in[cid]
  worldid = pair_worldid_in[cid]
  margin, gap = contact_margin_gap(geom_margin, geom_gap, pair_margin, pair_gap, geoms, pairid_in[cid][0], worldid)
  a, b, scale, res = _queued_patch(geom_type, geom_dataid, geom_size, geom_rbound, geom_xpos_in, geom_xmat_in, ms,
                                   wp.max(margin + gap, 0.0), geoms, worldid, patch_result[i], patch_pos[i])
  return a, b, scale, res, tilt_rotation(res.normal, mc_perturbation, j % NPERTURB, j // NPERTURB)


@functools.lru_cache(maxsize=None)
def pass_kernels(mode: int) -> SimpleNamespace:
  """The pass's kernels for support mode ``mode``, all in that mode's module (types.mode_module):
  ``face_pair``, ``manifold``, ``tilt``, ``tilt_mpr`` and ``patch``. manifold_kernel asks no
  support query, but sharing the module keeps the pass one module to compile."""
  module = mode_module(__name__, mode)
  face_pair = faceclip_funcs(mode).face_pair
  clip_faces = faceclip_funcs(mode).clip_faces
  tilts = tilt_funcs(mode)
  tilt_closed_form = tilts.tilt_closed_form
  tilt_mpr = tilts.tilt_mpr
  perturbed_contacts = tilts.perturbed_contacts

  @wp.kernel(module=module, cuda_max_registers=HEAVY_REGISTERS)
  def face_pair_kernel(
    # Model:
    geom_type: wp.array(dtype=int),
    geom_dataid: wp.array2d(dtype=int),
    geom_size: wp.array2d(dtype=wp.vec3),
    geom_rbound: wp.array2d(dtype=float),
    geom_margin: wp.array2d(dtype=float),
    geom_gap: wp.array2d(dtype=float),
    pair_margin: wp.array2d(dtype=float),
    pair_gap: wp.array2d(dtype=float),
    # Data in:
    geom_xpos_in: wp.array2d(dtype=wp.vec3),
    geom_xmat_in: wp.array2d(dtype=wp.mat33),
    # In:
    ms: MeshSupport,
    pair_in: wp.array(dtype=wp.vec2i),
    pairid_in: wp.array(dtype=wp.vec2i),
    pair_worldid_in: wp.array(dtype=int),
    patch_count: wp.array(dtype=int),
    patch_pair: wp.array(dtype=int),
    patch_result: wp.array(dtype=wp.vec4),
    nthread: int,
    # Out:
    face_count: wp.array(dtype=int),
    face_queue: wp.array(dtype=int),
    face_faces: wp.array(dtype=wp.vec3i),
    tilt_pair_count: wp.array(dtype=int),
    tilt_pair: wp.array(dtype=int),
  ):
    """The pairs convex_narrowphase queued for multi-contact, one thread a pair: those touching
    face on feature along the normal (faceclip.face_pair) are queued, with their faces, for
    manifold_kernel; the rest (edge on edge, curved surfaces, polygons over budget), by their
    index in the multi-contact queue, for the tilts (tilt_kernel, tilt_mpr_kernel, patch_kernel).
    Apart from the clipping, so that the support queries here and the clipping's loops there do
    not share one kernel's registers, and the clipping runs on dense warps of face pairs."""
    tid = wp.tid()
    for i in range(tid, patch_count[0], nthread):
      cid = patch_pair[i]
      geoms = pair_in[cid]
      worldid = pair_worldid_in[cid]
      margin, gap = contact_margin_gap(geom_margin, geom_gap, pair_margin, pair_gap, geoms, pairid_in[cid][0], worldid)
      a, b, _ = posed_pair(geom_type, geom_dataid, geom_size, geom_rbound, geom_xpos_in, geom_xmat_in, ms,
                           wp.max(margin + gap, 0.0), geoms, worldid)
      result = patch_result[i]
      faces = face_pair(a, b, ms, wp.vec3(result[0], result[1], result[2]))
      if faces[0] < 0:
        tilt_pair[wp.atomic_add(tilt_pair_count, 0, 1)] = i
      else:
        slot = wp.atomic_add(face_count, 0, 1)
        face_queue[slot] = i
        face_faces[slot] = faces

  @wp.kernel(module=module, cuda_max_registers=HEAVY_REGISTERS)
  def manifold_kernel(
    # Model:
    geom_type: wp.array(dtype=int),
    mixing: ContactMixing,
    geom_dataid: wp.array2d(dtype=int),
    geom_size: wp.array2d(dtype=wp.vec3),
    geom_rbound: wp.array2d(dtype=float),
    geom_aabb: wp.array3d(dtype=wp.vec3),
    # Data in:
    geom_xpos_in: wp.array2d(dtype=wp.vec3),
    geom_xmat_in: wp.array2d(dtype=wp.mat33),
    naconmax_in: int,
    # In:
    ms: MeshSupport,
    max_contacts: int,
    mc_tolerance: float,
    pair_in: wp.array(dtype=wp.vec2i),
    pairid_in: wp.array(dtype=wp.vec2i),
    pair_worldid_in: wp.array(dtype=int),
    patch_pair: wp.array(dtype=int),
    patch_result: wp.array(dtype=wp.vec4),
    patch_pos: wp.array(dtype=wp.vec3),
    face_count: wp.array(dtype=int),
    face_queue: wp.array(dtype=int),
    face_faces: wp.array(dtype=wp.vec3i),
    nthread: int,
    quota: ContactQuota,
    # Out:
    tilt_pair_count: wp.array(dtype=int),
    tilt_pair: wp.array(dtype=int),
    # Data out:
    contacts_out: ContactRows,
  ):
    """The pairs face_pair_kernel queued for face clipping, one thread a pair: the faces it found
    clipped (faceclip.clip_faces) give the contacts; a pair whose corners all lie above the
    band goes on to the tilts after all."""
    tid = wp.tid()
    for s in range(tid, face_count[0], nthread):
      i = face_queue[s]
      cid = patch_pair[i]
      geoms = pair_in[cid]
      worldid = pair_worldid_in[cid]
      # the contact parameters are read once the clipping is done: held through it, they took
      # registers it needed
      margin, gap = contact_margin_gap(mixing.geom_margin, mixing.geom_gap, mixing.pair_margin,
                                       mixing.pair_gap, geoms, pairid_in[cid][0], worldid)
      band = wp.max(margin + gap, 0.0)
      a, b, scale, res = _queued_patch(geom_type, geom_dataid, geom_size, geom_rbound, geom_xpos_in, geom_xmat_in, ms, band,
                                       geoms, worldid, patch_result[i], patch_pos[i])
      # duplicates: closer than mc_tolerance x the smaller geom's box size (as patch_kernel's)
      ab = worldid % geom_aabb.shape[0]
      size = 2.0 * wp.min(wp.length(geom_aabb[ab, geoms[0], 1]), wp.length(geom_aabb[ab, geoms[1], 1]))
      found = clip_faces(a, b, ms, res, scale, max_contacts, mc_tolerance * size, face_faces[s])
      # the pair read again, not held through the clipping
      i = face_queue[s]
      if found.status == TILTS:
        tilt_pair[wp.atomic_add(tilt_pair_count, 0, 1)] = i
        continue
      cid = patch_pair[i]
      geoms = pair_in[cid]
      worldid = pair_worldid_in[cid]
      _, margin, gap, condim, friction, solref, solreffriction, solimp, adhesion = mixed_params(
        mixing, pair_in, pairid_in, cid, worldid)
      band = wp.max(margin + gap, 0.0)
      res = _queued_first(patch_result[i], patch_pos[i])
      frame = make_frame(res.normal)
      # the clipped corners lie in the reference shape's frame: its pose read again here, not held
      # through the clipping
      ref_geom = geoms[wp.where(found.ref_is_b, 1, 0)]
      rot = geom_xmat_in[worldid, ref_geom]
      shift = geom_xpos_in[worldid, ref_geom]
      for k in range(found.n):
        pos = rot @ manifold_pos(found, k) + shift
        if k == found.first:
          pos = res.pos - 0.5 * band * res.normal
        write_row(
          quota, worldid, naconmax_in, k, manifold_dist(found, k), pos, frame, margin, gap, condim, friction, solref,
          solreffriction, solimp, adhesion, geoms, pairid_in[cid], contacts_out,
        )

  @wp.kernel(module=module, cuda_max_registers=HEAVY_REGISTERS)
  def tilt_kernel(
    # Model:
    geom_type: wp.array(dtype=int),
    geom_dataid: wp.array2d(dtype=int),
    geom_size: wp.array2d(dtype=wp.vec3),
    geom_rbound: wp.array2d(dtype=float),
    geom_margin: wp.array2d(dtype=float),
    geom_gap: wp.array2d(dtype=float),
    pair_margin: wp.array2d(dtype=float),
    pair_gap: wp.array2d(dtype=float),
    # Data in:
    geom_xpos_in: wp.array2d(dtype=wp.vec3),
    geom_xmat_in: wp.array2d(dtype=wp.mat33),
    # In:
    ms: MeshSupport,
    mc_perturbation: float,
    pair_in: wp.array(dtype=wp.vec2i),
    pairid_in: wp.array(dtype=wp.vec2i),
    pair_worldid_in: wp.array(dtype=int),
    tilt_pair_count: wp.array(dtype=int),
    tilt_pair: wp.array(dtype=int),
    patch_pair: wp.array(dtype=int),
    patch_result: wp.array(dtype=wp.vec4),
    patch_pos: wp.array(dtype=wp.vec3),
    nthread: int,
    # Out:
    tilt_result: wp.array2d(dtype=wp.vec4),
    tilt_count: wp.array(dtype=int),
    tilt_queue: wp.array(dtype=int),
  ):
    """Both attempts of each of the four tilts of the pairs left to the tilts by face_pair_kernel
    and manifold_kernel (row q of tilt_result: the q-th of them), one thread an attempt, in closed form
    (multicontact.tilt_closed_form); the attempts it cannot answer are queued for tilt_mpr_kernel,
    so the tilted MPRs run on dense warps. The steeper attempt is computed whether or not
    patch_kernel's replay needs it: most first attempts land back on the first contact and need
    it."""
    tid = wp.tid()
    nattempt = 2 * NPERTURB
    for j in range(tid, wp.min(tilt_pair_count[0], tilt_result.shape[0]) * nattempt, nthread):
      q = j // nattempt
      i = tilt_pair[q]
      a, b, scale, res, rot = _queued_tilt(geom_type, geom_dataid, geom_size, geom_rbound, geom_margin, geom_gap,
                                           pair_margin, pair_gap, geom_xpos_in, geom_xmat_in, ms, mc_perturbation,
                                           pair_in, pairid_in, pair_worldid_in, patch_pair, patch_result, patch_pos, i,
                                           j % nattempt)
      answer = tilt_closed_form(a, b, ms, res, scale, rot)
      tilt_result[q, j % nattempt] = answer
      if answer[3] == UNKNOWN:
        tilt_queue[wp.atomic_add(tilt_count, 0, 1)] = j

  @wp.kernel(module=module, cuda_max_registers=HEAVY_REGISTERS)
  def tilt_mpr_kernel(
    # Model:
    geom_type: wp.array(dtype=int),
    geom_dataid: wp.array2d(dtype=int),
    geom_size: wp.array2d(dtype=wp.vec3),
    geom_rbound: wp.array2d(dtype=float),
    geom_margin: wp.array2d(dtype=float),
    geom_gap: wp.array2d(dtype=float),
    pair_margin: wp.array2d(dtype=float),
    pair_gap: wp.array2d(dtype=float),
    # Data in:
    geom_xpos_in: wp.array2d(dtype=wp.vec3),
    geom_xmat_in: wp.array2d(dtype=wp.mat33),
    # In:
    ms: MeshSupport,
    mpr_options: MprSettings,
    mc_perturbation: float,
    pair_in: wp.array(dtype=wp.vec2i),
    pairid_in: wp.array(dtype=wp.vec2i),
    pair_worldid_in: wp.array(dtype=int),
    tilt_pair: wp.array(dtype=int),
    patch_pair: wp.array(dtype=int),
    patch_result: wp.array(dtype=wp.vec4),
    patch_pos: wp.array(dtype=wp.vec3),
    tilt_count: wp.array(dtype=int),
    tilt_queue: wp.array(dtype=int),
    nthread: int,
    # Out:
    tilt_result: wp.array2d(dtype=wp.vec4),
  ):
    """The tilted MPRs of the attempts tilt_kernel queued (edge against edge, or a foot beside
    the face), one thread an attempt."""
    tid = wp.tid()
    nattempt = 2 * NPERTURB
    for s in range(tid, tilt_count[0], nthread):
      j = tilt_queue[s]
      q = j // nattempt
      i = tilt_pair[q]
      a, b, scale, res, rot = _queued_tilt(geom_type, geom_dataid, geom_size, geom_rbound, geom_margin, geom_gap,
                                           pair_margin, pair_gap, geom_xpos_in, geom_xmat_in, ms, mc_perturbation,
                                           pair_in, pairid_in, pair_worldid_in, patch_pair, patch_result, patch_pos, i,
                                           j % nattempt)
      tilt_result[q, j % nattempt] = tilt_mpr(a, b, ms, res, scale, mpr_options.tolerance,
                                              mpr_options.iterations, rot)

  @wp.kernel(module=module, cuda_max_registers=HEAVY_REGISTERS)
  def patch_kernel(
    # Model:
    geom_type: wp.array(dtype=int),
    mixing: ContactMixing,
    geom_dataid: wp.array2d(dtype=int),
    geom_size: wp.array2d(dtype=wp.vec3),
    geom_rbound: wp.array2d(dtype=float),
    geom_aabb: wp.array3d(dtype=wp.vec3),
    # Data in:
    geom_xpos_in: wp.array2d(dtype=wp.vec3),
    geom_xmat_in: wp.array2d(dtype=wp.mat33),
    naconmax_in: int,
    # In:
    ms: MeshSupport,
    mpr_options: MprSettings,
    max_contacts: int,
    mc_perturbation: float,
    mc_tolerance: float,
    pair_in: wp.array(dtype=wp.vec2i),
    pairid_in: wp.array(dtype=wp.vec2i),
    pair_worldid_in: wp.array(dtype=int),
    tilt_pair_count: wp.array(dtype=int),
    tilt_pair: wp.array(dtype=int),
    patch_pair: wp.array(dtype=int),
    patch_result: wp.array(dtype=wp.vec4),
    patch_pos: wp.array(dtype=wp.vec3),
    tilt_result: wp.array2d(dtype=wp.vec4),
    nthread: int,
    quota: ContactQuota,
    # Data out:
    contacts_out: ContactRows,
  ):
    """The pairs left to the tilts (face_pair_kernel, manifold_kernel): the tilts, then all their
    contacts.

    A separate kernel so that warps run only pairs that need the tilts: in the convex kernel one
    such pair held its whole warp. The tilts come from tilt_kernel and
    tilt_mpr_kernel for the first ``len(tilt_result)`` queued pairs; this kernel replays the tilt
    logic with them, and computes the tilts itself for any pair beyond.
    """
    tid = wp.tid()
    for q in range(tid, tilt_pair_count[0], nthread):
      i = tilt_pair[q]
      cid = patch_pair[i]
      geoms = pair_in[cid]
      g1 = geoms[0]
      g2 = geoms[1]
      worldid = pair_worldid_in[cid]
      _, margin, gap, condim, friction, solref, solreffriction, solimp, adhesion = mixed_params(
        mixing, pair_in, pairid_in, cid, worldid)
      band = wp.max(margin + gap, 0.0)
      a, b, scale, res = _queued_patch(geom_type, geom_dataid, geom_size, geom_rbound, geom_xpos_in, geom_xmat_in, ms, band,
                                       geoms, worldid, patch_result[i], patch_pos[i])
      # duplicates: closer than mc_tolerance x the smaller geom's box size
      ab = worldid % geom_aabb.shape[0]
      size = 2.0 * wp.min(wp.length(geom_aabb[ab, g1, 1]), wp.length(geom_aabb[ab, g2, 1]))
      extra = perturbed_contacts(a, b, ms, res, scale, mpr_options.tolerance, mpr_options.iterations,
                                 mc_perturbation, mc_tolerance * size, tilt_result,
                                 wp.where(q < tilt_result.shape[0], q, -1))
      write_pair_contacts(
        res, extra, mc_tolerance * size, mpr_options.tolerance * scale, max_contacts, band, naconmax_in, margin, gap,
        condim, friction, solref, solreffriction, solimp, adhesion, geoms, pairid_in[cid], worldid, contacts_out, quota,
      )

  return SimpleNamespace(face_pair=face_pair_kernel, manifold=manifold_kernel, tilt=tilt_kernel,
                         tilt_mpr=tilt_mpr_kernel, patch=patch_kernel)





class MultiContactPass:
  """The multi-contact pass: what it reads of the model and the step's launches; its queues are
  the narrow phase's buffers, which the MPR kernel fills (the stage contract: docs/architecture.md)."""

  def __init__(self, options: Options, support_mode: SupportMode, mesh_support: MeshSupport, mpr_types: tuple):
    self.options, self.support_mode, self.mesh_support = options, support_mode, mesh_support
    self.mpr_types = mpr_types  # no MPR pair, nothing queued

  def make_buffers(self, d, st) -> None:
    """None: the pass works in the narrow phase's buffers."""
    return None

  def launch(self, m, d, st) -> None:
    """The multi-contact pass over the pairs the MPR kernel queued: face pairs, face clipping, the
    tilts and their MPRs, then each tilted pair's contacts."""
    pairs, b, quota = st.broad, st.narrow, st.quota.quota
    if not self.mpr_types:
      return
    opt = self.options
    kernels = pass_kernels(self.support_mode)
    nthread = max(1, min(pairs.capacity, GRID_THREADS))
    nthread_tilt = max(1, min(b.tilt_result.shape[0] * b.tilt_result.shape[1], GRID_THREADS))
    pair, pairid, pair_worldid = pairs.pair, pairs.pairid, pairs.pair_worldid
    wp.launch(
      kernels.face_pair,
      dim=nthread,
      inputs=[
        m.geom_type, m.geom_dataid, m.geom_size, m.geom_rbound, m.geom_margin, m.geom_gap, m.pair_margin,
        m.pair_gap, d.geom_xpos, d.geom_xmat, self.mesh_support,
        pair, pairid, pair_worldid, b.patch_count, b.patch_pair, b.patch_result, nthread,
      ],
      outputs=[b.face_count, b.face_queue, b.face_faces, b.tilt_pair_count, b.tilt_pair],
    )
    wp.launch(
      kernels.manifold,
      dim=nthread,
      inputs=[
        m.geom_type, contact_mixing(m), m.geom_dataid, m.geom_size, m.geom_rbound, m.geom_aabb,
        d.geom_xpos, d.geom_xmat, d.naconmax, self.mesh_support,
        opt.max_contacts_per_pair, opt.mc_tolerance, pair, pairid, pair_worldid,
        b.patch_pair, b.patch_result, b.patch_pos, b.face_count, b.face_queue, b.face_faces, nthread,
        quota,
      ],
      outputs=[b.tilt_pair_count, b.tilt_pair] + contact_outputs(d),
    )
    tilt_model = [m.geom_type, m.geom_dataid, m.geom_size, m.geom_rbound, m.geom_margin, m.geom_gap, m.pair_margin,
                  m.pair_gap, d.geom_xpos, d.geom_xmat, self.mesh_support]
    wp.launch(
      kernels.tilt,
      dim=nthread_tilt,
      inputs=tilt_model + [opt.mc_perturbation, pair, pairid, pair_worldid, b.tilt_pair_count,
                           b.tilt_pair, b.patch_pair, b.patch_result, b.patch_pos, nthread_tilt],
      outputs=[b.tilt_result, b.tilt_count, b.tilt_queue],
    )
    wp.launch(
      kernels.tilt_mpr,
      dim=nthread_tilt,
      inputs=tilt_model + [settings_of(opt), opt.mc_perturbation,
                           pair, pairid, pair_worldid, b.tilt_pair, b.patch_pair, b.patch_result,
                           b.patch_pos, b.tilt_count, b.tilt_queue, nthread_tilt],
      outputs=[b.tilt_result],
    )
    wp.launch(
      kernels.patch,
      dim=nthread,
      inputs=[
        m.geom_type, contact_mixing(m), m.geom_dataid, m.geom_size, m.geom_rbound, m.geom_aabb,
        d.geom_xpos, d.geom_xmat, d.naconmax, self.mesh_support, settings_of(opt),
        opt.max_contacts_per_pair, opt.mc_perturbation, opt.mc_tolerance, pair,
        pairid, pair_worldid, b.tilt_pair_count, b.tilt_pair, b.patch_pair, b.patch_result, b.patch_pos,
        b.tilt_result, nthread, quota,
      ],
      outputs=contact_outputs(d),
    )
