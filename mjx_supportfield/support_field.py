"""Builds the support field of every mesh from MuJoCo's convex hulls."""

import dataclasses

import mujoco
import numpy as np
import warp as wp

from mjx_supportfield.types import MeshSupport


@dataclasses.dataclass
class HullData:
  """Host-side hull description of all meshes (local vertex ids, neighbour lists)."""

  hull_adr: np.ndarray
  hull_num: np.ndarray
  hull_vert: np.ndarray
  hull_center: np.ndarray
  nbr_adr: np.ndarray
  nbr_num: np.ndarray
  nbr: np.ndarray


def mesh_hull(mjm: mujoco.MjModel, meshid: int):
  """Hull vertex ids (within the mesh) and neighbour lists of one mesh.

  Uses MuJoCo's convex-hull graph; a mesh without one uses all its vertices and no
  neighbours (support queries then scan or use the field alone).
  """
  adr = mjm.mesh_graphadr[meshid]
  if adr < 0:
    n = int(mjm.mesh_vertnum[meshid])
    return np.arange(n, dtype=np.int32), [[] for _ in range(n)]
  g = mjm.mesh_graph
  nv = int(g[adr])
  edgeadr = g[adr + 2 : adr + 2 + nv]
  globalid = np.array(g[adr + 2 + nv : adr + 2 + 2 * nv], dtype=np.int32)
  edges = g[adr + 2 + 2 * nv :]
  nbrs = []
  for i in range(nv):
    k = int(edgeadr[i])
    lst = []
    while edges[k] >= 0:
      lst.append(int(edges[k]))
      k += 1
    nbrs.append(lst)
  return globalid, nbrs


def hull_data(mjm: mujoco.MjModel) -> HullData:
  """Flattens the hulls of all meshes of a model."""
  hull_adr, hull_num, hull_vert, centers, nbr_num, nbr = [], [], [], [], [], []
  total = 0
  for meshid in range(mjm.nmesh):
    verts, nbrs = mesh_hull(mjm, meshid)
    hull_adr.append(total)
    hull_num.append(len(verts))
    total += len(verts)
    hull_vert.append(verts)
    vadr = mjm.mesh_vertadr[meshid]
    centers.append(mjm.mesh_vert[vadr + verts].mean(axis=0) if len(verts) else np.zeros(3))
    nbr_num.extend(len(x) for x in nbrs)
    nbr.extend(v for x in nbrs for v in x)
  nbr_num = np.array(nbr_num, dtype=np.int32)
  nbr_adr = np.concatenate([[0], np.cumsum(nbr_num)[:-1]]).astype(np.int32) if len(nbr_num) else np.zeros(0, np.int32)
  return HullData(
    hull_adr=np.array(hull_adr, dtype=np.int32),
    hull_num=np.array(hull_num, dtype=np.int32),
    hull_vert=np.concatenate(hull_vert).astype(np.int32) if hull_vert else np.zeros(0, np.int32),
    hull_center=np.array(centers, dtype=np.float32).reshape(-1, 3),
    nbr_adr=nbr_adr,
    nbr_num=nbr_num,
    nbr=np.array(nbr, dtype=np.int32),
  )


@wp.func
def cell_direction(i: int, j: int, res: int) -> wp.vec3:
  """Direction of field cell (i, j): theta = 2 pi i / res - pi, phi = pi j / (res - 1)."""
  theta = 2.0 * wp.pi * float(i) / float(res) - wp.pi
  phi = wp.pi * float(j) / float(res - 1)
  return wp.vec3(wp.sin(phi) * wp.cos(theta), wp.sin(phi) * wp.sin(theta), wp.cos(phi))


@wp.kernel
def _build_field(
  ms: MeshSupport,
  cell_mesh: wp.array(dtype=int),
  # out
  field_out: wp.array(dtype=int),
):
  cell = wp.tid()
  mesh = cell_mesh[cell]
  res = ms.field_res[mesh]
  local_cell = cell - ms.field_adr[mesh]
  d = cell_direction(local_cell % res, local_cell // res, res)
  hadr = ms.hull_adr[mesh]
  vadr = ms.vertadr[mesh]
  best = int(0)
  best_dot = float(-1.0e30)
  for k in range(ms.hull_num[mesh]):
    kd = wp.dot(ms.vert[vadr + ms.hull_vert[hadr + k]], d)
    if kd > best_dot:
      best = k
      best_dot = kd
  field_out[cell] = best


def build_mesh_support(mjm: mujoco.MjModel, mesh_vert: wp.array, res: int, device=None) -> MeshSupport:
  """Builds MeshSupport (hulls, neighbour lists and one field per mesh) on the device.

  ``mesh_vert`` is MuJoCo Warp's device copy of the mesh vertices (shared, not copied).
  """
  hd = hull_data(mjm)
  nmesh = mjm.nmesh
  ms = MeshSupport()

  def arr(x, dtype=int):
    return wp.array(x, dtype=dtype, device=device)

  ms.vert = mesh_vert
  ms.vertadr = arr(np.asarray(mjm.mesh_vertadr, dtype=np.int32) if nmesh else np.zeros(0, np.int32))
  ms.hull_adr = arr(hd.hull_adr)
  ms.hull_num = arr(hd.hull_num)
  ms.hull_center = arr(hd.hull_center, wp.vec3)
  ms.hull_vert = arr(hd.hull_vert)
  ms.nbr_adr = arr(hd.nbr_adr)
  ms.nbr_num = arr(hd.nbr_num)
  ms.nbr = arr(hd.nbr)
  field_res = np.full(nmesh, res, dtype=np.int32)
  field_res[hd.hull_num == 0] = 0
  field_adr = np.concatenate([[0], np.cumsum(field_res.astype(np.int64) ** 2)]).astype(np.int64)
  ncell = int(field_adr[-1])
  ms.field_res = arr(field_res)
  ms.field_adr = arr(field_adr[:-1].astype(np.int32))
  ms.field = wp.zeros(max(ncell, 1), dtype=int, device=device)
  if ncell:
    cell_mesh = np.repeat(np.arange(nmesh, dtype=np.int32), field_res.astype(np.int64) ** 2)
    wp.launch(_build_field, dim=ncell, inputs=[ms, arr(cell_mesh)], outputs=[ms.field], device=device)
  return ms


def field_bytes(ms: MeshSupport, meshid: int) -> int:
  """Bytes the support field of one mesh occupies (cells only)."""
  res = int(ms.field_res.numpy()[meshid])
  return res * res * wp.types.type_size_in_bytes(ms.field.dtype)
