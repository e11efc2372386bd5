"""Device-side types shared by the pipeline stages."""

import enum

import warp as wp
from mujoco_warp._src.types import GeomType

# beyond any distance, depth or coordinate of a scene: the start of a search for a minimum (or,
# negated, a maximum) and the sentinel of an empty answer
FAR = 1.0e30


class SupportMode(enum.IntEnum):
  """Options.support_mode as the kernel factories take it: fixed when a kernel is generated, not
  a kernel input. The Collider turns the option's name into one once (``SupportMode.of``)."""

  FIELD = 0
  REFINED = 1
  EXACT = 2

  @classmethod
  def of(cls, name: str) -> "SupportMode":
    """The mode of an Options.support_mode name ("field", "refined", "exact")."""
    return cls[name.upper()]


SUPPORT_FIELD, SUPPORT_REFINED, SUPPORT_EXACT = SupportMode.FIELD, SupportMode.REFINED, SupportMode.EXACT

# convex geom types: the plugin's own narrow phase (MPR or analytic), also against heightfields
CONVEX_TYPES = (GeomType.SPHERE, GeomType.CAPSULE, GeomType.ELLIPSOID, GeomType.CYLINDER, GeomType.BOX, GeomType.MESH)
# geom types whose pairs go to stock MuJoCo Warp
STOCK_TYPES = (GeomType.SDF,)

# Warp module options of every plugin module: no adjoints (nothing differentiates through the
# collision stage), and CPU code for any host of the target (no -march=native), so that a prebuilt
# CPU module (launch/prebuilt.py) fits every machine and a CPU's contacts are the same bits on each
MODULE_OPTIONS = {"enable_backward": False, "cpu_compiler_flags": ""}
# the same for a factory's module="unique" kernel, which takes Warp's global options, not its
# Python module's (it turns adjoints off in its decorator)
UNIQUE_MODULE_OPTIONS = {"cpu_compiler_flags": ""}


def mode_module(name: str, mode: int, part: str = "") -> str:
  """The Warp module that module ``name``'s kernels for support mode ``mode`` are built in, with
  ``name``'s module options (MODULE_OPTIONS, fuse_fp); with ``part``, one of that stage's modules.

  One module a mode: a model compiles only the kernels of its own mode, and a second mode in the
  same process adds its own modules instead of rebuilding the first's with both. A stage splits
  its kernels into parts where one module would take minutes to build on a GPU: the parts build
  side by side at first use (first_use.py). Call it once a mode and part (from an lru_cache'd
  kernel factory): setting the options marks the module modified.
  """
  module = f"{name}.{SupportMode(mode).name.lower()}" + (f".{part}" if part else "")
  wp.set_module_options(dict(wp.get_module_options(name)), module=module)
  return module


@wp.struct
class MeshSupport:
  """Convex-hull data and support fields of all meshes, flattened with per-mesh offsets.

  Hull vertices are numbered globally (``hull_adr[mesh] + local``); the field stores local
  indices so one cell costs 2 bytes. ``hull_pos`` copies the hull vertices' positions out of
  ``vert`` at install, so a support query gathers a point with one read instead of two.
  """

  vert: wp.array(dtype=wp.vec3)  # MuJoCo's mesh_vert, mesh frame
  vertadr: wp.array(dtype=int)  # per mesh: first vertex in vert
  hull_adr: wp.array(dtype=int)  # per mesh: first hull vertex
  hull_num: wp.array(dtype=int)  # per mesh: number of hull vertices
  hull_center: wp.array(dtype=wp.vec3)  # per mesh: mean of the hull vertices (interior point)
  hull_vert: wp.array(dtype=int)  # per hull vertex: vertex index within its mesh
  hull_pos: wp.array(dtype=wp.vec3)  # per hull vertex: its position, mesh frame
  nbr_adr: wp.array(dtype=int)  # per hull vertex: first neighbour in nbr
  nbr_num: wp.array(dtype=int)  # per hull vertex: number of neighbours
  nbr: wp.array(dtype=int)  # neighbour hull vertices (local indices)
  field_adr: wp.array(dtype=int)  # per mesh: first cell of its field
  field_res: wp.array(dtype=int)  # per mesh: field resolution (0: no field)
  field: wp.array(dtype=wp.uint16)  # per cell: local hull index of the support vertex, proof code
  extra_adr: wp.array(dtype=int)  # per mesh: first entry of its extras lists in extra
  extra: wp.array(dtype=wp.uint16)  # extras lists of WITH_EXTRAS quads (see support.py)
  plane_adr: wp.array(dtype=int)  # per mesh: first hull face plane
  plane_num: wp.array(dtype=int)  # per mesh: hull face planes (0: none known)
  plane: wp.array(dtype=wp.vec4)  # hull face planes: outward unit normal, offset (mesh frame)
  # MuJoCo's hull polygons (coplanar triangles merged), for telling whether a point lies on a face
  poly_adr: wp.array(dtype=int)  # per mesh: first polygon
  poly_normal: wp.array(dtype=wp.vec3)  # per polygon: outward unit normal (mesh frame)
  poly_vert_adr: wp.array(dtype=int)  # per polygon: first corner in poly_pos
  poly_vert_num: wp.array(dtype=int)  # per polygon: corners (0: unusable)
  # corners in order, their positions (mesh frame): a face's corner is one read, as hull_pos's
  # support point is, where a hull index would be a chain of dependent loads
  poly_pos: wp.array(dtype=wp.vec3)
  vert_poly_adr: wp.array(dtype=int)  # per hull vertex: first entry in vert_poly
  vert_poly_num: wp.array(dtype=int)  # per hull vertex: polygons it is a corner of
  vert_poly: wp.array(dtype=int)  # polygons (indices within the mesh) around each hull vertex


@wp.struct
class Shape:
  """A convex geom posed in the world, as seen by the support functions."""

  gtype: int
  pos: wp.vec3
  rot: wp.mat33
  size: wp.vec3
  mesh: int  # mesh id for MESH geoms, else -1
  center: wp.vec3  # interior point (world)
  inflate: float  # radius added to the support (margin handling)
