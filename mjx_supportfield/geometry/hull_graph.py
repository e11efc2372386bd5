"""MuJoCo's compiled convex hull of a mesh (``mesh_graph``), parsed once for every reader.

The support fields (neighbour lists, face planes), the SDF bake (hull triangles) and the host
yardstick ``exact`` (hull vertices and triangles) all read the same graph; this module holds its
layout, in numpy only, so the Warp-free ``exact`` can use it too.
"""

import dataclasses
from typing import Optional

import mujoco
import numpy as np

NBR_END = -1  # ends each hull vertex's neighbour list in the graph


@dataclasses.dataclass(frozen=True)
class HullGraph:
  """One mesh's convex hull as MuJoCo compiled it.

  MuJoCo stores it as numvert, numface, vert_edgeadr[numvert], vert_globalid[numvert],
  edge_localid[numvert + 3 numface] (per hull vertex, its neighbours as local hull indices,
  ended by -1, back to back), face_globalid[3 numface].
  """

  vert: np.ndarray  # (nvert,) int32: hull vertices as vertex ids within the mesh
  nbr_num: np.ndarray  # (nvert,) int32: neighbours of each hull vertex
  nbr: np.ndarray  # int32: the neighbour lists back to back, local hull indices, without the ends
  faces: np.ndarray  # (nface, 3) int32: hull triangles as vertex ids within the mesh


def hull_graph(mjm: mujoco.MjModel, meshid: int) -> Optional[HullGraph]:
  """The convex hull MuJoCo compiled for a mesh, or None for a mesh it built none for.

  Raises ValueError when the graph does not have the layout above, since every reader would
  otherwise take neighbours or faces from the wrong entries.
  """
  adr = int(mjm.mesh_graphadr[meshid])
  if adr < 0:
    return None
  graph = mjm.mesh_graph
  nvert, nface = int(graph[adr]), int(graph[adr + 1])
  edge_adr_start = adr + 2
  vert_start = edge_adr_start + nvert
  edge_start = vert_start + nvert
  face_start = edge_start + nvert + 3 * nface
  edge_adr = np.asarray(graph[edge_adr_start:vert_start], dtype=np.int64)
  edges = np.asarray(graph[edge_start:face_start])
  ends = np.nonzero(edges == NBR_END)[0]
  if (nvert == 0 or len(ends) != nvert or ends[-1] != len(edges) - 1 or edge_adr[0] != 0
      or np.any(edge_adr[1:] != ends[:-1] + 1)):
    raise ValueError(f"mesh {meshid}: MuJoCo's convex-hull graph has an unexpected layout")
  return HullGraph(
    vert=np.asarray(graph[vert_start:edge_start], dtype=np.int32),
    nbr_num=(ends - edge_adr).astype(np.int32),
    nbr=edges[edges != NBR_END].astype(np.int32),
    faces=np.asarray(graph[face_start : face_start + 3 * nface], dtype=np.int32).reshape(nface, 3),
  )
