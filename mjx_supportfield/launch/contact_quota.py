"""Contact rows owned per world (``Options.contacts_per_world``).

MuJoCo Warp's writers append to ``d.contact`` through one atomic counter, ``d.nacon``, shared by
every world: when the buffer overflows, whichever writers come first keep their contacts, so a
world with a pile of contacts can take another world's rows. With a quota of N rows a world,
world w writes rows [w*N, (w+1)*N) through its own counter instead: every writer gets views of
the contact arrays that start at the world's first row (``world_rows``), so MuJoCo Warp's
routines, which index from 0 and stop at the limit they are given, stay unchanged. A world past
its quota loses its own contacts only. After the narrow phase the rows are packed to the front
(world by world, each world's rows in the order they were written) and ``d.nacon`` counts them.

Every writer picks its rows here, in one of two ways. A writer of single rows calls
``write_row``: with N = 0 it writes the contact arrays themselves, else its world's views. A kernel
that hands the rows to MuJoCo Warp's routines (they call write_contact themselves) is built per
quota and takes its rows from ``rows(per_world)``, a choice made when the kernel is built: without a
quota the routines get the arrays themselves, not fifteen views held in registers through them.

This module owns the quota's kernels, its per-Data buffers (``make_buffers``) and its host entries
(``start`` before the writers, ``pack`` after them), and the two structs every writer takes:
``ContactRows``, the contact arrays and counter it writes (``contact_rows``), and ``ContactMixing``,
the model arrays its contact parameters are mixed from (``contact_mixing``, ``mixed_params``).
"""

import dataclasses

import warp as wp
from mujoco_warp._src.collision_core import contact_params
from mujoco_warp._src.collision_core import write_contact
from mujoco_warp._src.types import OverflowType
from mujoco_warp._src.types import vec5

from mjx_supportfield.launch import contact_sort
from mjx_supportfield.launch.contact_sort import ContactFields
from mjx_supportfield.types import MODULE_OPTIONS

wp.set_module_options(MODULE_OPTIONS)

# bytes of one row of each contact field
_INT = wp.constant(wp.types.type_size_in_bytes(wp.int32))
_FLOAT = wp.constant(wp.types.type_size_in_bytes(wp.float32))
_VEC2 = wp.constant(wp.types.type_size_in_bytes(wp.vec2))
_VEC2I = wp.constant(wp.types.type_size_in_bytes(wp.vec2i))
_VEC3 = wp.constant(wp.types.type_size_in_bytes(wp.vec3))
_VEC5 = wp.constant(wp.types.type_size_in_bytes(vec5))
_MAT33 = wp.constant(wp.types.type_size_in_bytes(wp.mat33))


@wp.struct
class ContactQuota:
  """Where a world's contacts go: ``per_world`` rows each (0: the shared buffer)."""

  per_world: int
  world_ncon: wp.array(dtype=int)  # contacts each world found (those beyond per_world included)


@wp.struct
class ContactRows:
  """What the plugin's contact writers write: d.contact's arrays (WRITTEN_CONTACT_FIELDS) and
  d.nacon, one kernel argument (contact_rows). Unpacked where MuJoCo Warp's write_contact takes
  them, as the row views of a world (world_rows) or the arrays themselves (shared_rows)."""

  dist: wp.array(dtype=float)
  pos: wp.array(dtype=wp.vec3)
  frame: wp.array(dtype=wp.mat33)
  includemargin: wp.array(dtype=float)
  friction: wp.array(dtype=vec5)
  solref: wp.array(dtype=wp.vec2)
  solreffriction: wp.array(dtype=wp.vec2)
  solimp: wp.array(dtype=vec5)
  dim: wp.array(dtype=int)
  geom: wp.array(dtype=wp.vec2i)
  efc_address: wp.array2d(dtype=int)
  worldid: wp.array(dtype=int)
  type: wp.array(dtype=int)
  geomcollisionid: wp.array(dtype=int)
  adhesion: wp.array(dtype=float)
  nacon: wp.array(dtype=int)


@wp.struct
class ContactMixing:
  """The model's arrays MuJoCo mixes a pair's contact parameters from (MuJoCo Warp's
  collision_core.contact_params): one kernel argument (contact_mixing), unpacked in mixed_params."""

  geom_condim: wp.array(dtype=int)
  geom_priority: wp.array(dtype=int)
  geom_solmix: wp.array2d(dtype=float)
  geom_solref: wp.array2d(dtype=wp.vec2)
  geom_solimp: wp.array2d(dtype=vec5)
  geom_friction: wp.array2d(dtype=wp.vec3)
  geom_margin: wp.array2d(dtype=float)
  geom_gap: wp.array2d(dtype=float)
  geom_adhesion: wp.array2d(dtype=float)
  pair_dim: wp.array(dtype=int)
  pair_solref: wp.array2d(dtype=wp.vec2)
  pair_solreffriction: wp.array2d(dtype=wp.vec2)
  pair_solimp: wp.array2d(dtype=vec5)
  pair_margin: wp.array2d(dtype=float)
  pair_gap: wp.array2d(dtype=float)
  pair_adhesion: wp.array2d(dtype=float)
  pair_friction: wp.array2d(dtype=vec5)


@wp.func
def mixed_params(mixing: ContactMixing, pair_in: wp.array(dtype=wp.vec2i), pairid_in: wp.array(dtype=wp.vec2i),
                 cid: int, worldid: int):
  """MuJoCo Warp's contact_params of pair ``cid``: (geom pair, margin, gap, condim, friction,
  solref, solreffriction, solimp, adhesion)."""
  return contact_params(
    mixing.geom_condim, mixing.geom_priority, mixing.geom_solmix, mixing.geom_solref, mixing.geom_solimp,
    mixing.geom_friction, mixing.geom_margin, mixing.geom_gap, mixing.geom_adhesion, mixing.pair_dim,
    mixing.pair_solref, mixing.pair_solreffriction, mixing.pair_solimp, mixing.pair_margin, mixing.pair_gap,
    mixing.pair_adhesion, mixing.pair_friction, pair_in, pairid_in, cid, worldid,
  )


@wp.func
def _offset(ptr: wp.uint64, row: int, row_bytes: int) -> wp.uint64:
  """Address of row ``row`` of a contiguous array (in 64 bits: rows x bytes can pass 2**31)."""
  return ptr + wp.uint64(row) * wp.uint64(row_bytes)


@wp.func
def world_rows(
  quota: ContactQuota,
  worldid: int,
  naconmax_in: int,
  contacts_out: ContactRows,
):
  """The contact rows world ``worldid`` may write, as MuJoCo Warp's write_contact takes them: the
  row limit, the 15 contact arrays and the counter. With a quota, views of the world's rows and
  its own counter; without, the whole arrays and ``d.nacon``."""
  start = int(0)
  n = naconmax_in
  counter = contacts_out.nacon.ptr
  if quota.per_world > 0:
    start = worldid * quota.per_world
    n = quota.per_world
    counter = _offset(quota.world_ncon.ptr, worldid, _INT)
  k = contacts_out.efc_address.shape[1]
  return (
    n,
    wp.array(ptr=_offset(contacts_out.dist.ptr, start, _FLOAT), shape=(n,), dtype=float),
    wp.array(ptr=_offset(contacts_out.pos.ptr, start, _VEC3), shape=(n,), dtype=wp.vec3),
    wp.array(ptr=_offset(contacts_out.frame.ptr, start, _MAT33), shape=(n,), dtype=wp.mat33),
    wp.array(ptr=_offset(contacts_out.includemargin.ptr, start, _FLOAT), shape=(n,), dtype=float),
    wp.array(ptr=_offset(contacts_out.friction.ptr, start, _VEC5), shape=(n,), dtype=vec5),
    wp.array(ptr=_offset(contacts_out.solref.ptr, start, _VEC2), shape=(n,), dtype=wp.vec2),
    wp.array(ptr=_offset(contacts_out.solreffriction.ptr, start, _VEC2), shape=(n,), dtype=wp.vec2),
    wp.array(ptr=_offset(contacts_out.solimp.ptr, start, _VEC5), shape=(n,), dtype=vec5),
    wp.array(ptr=_offset(contacts_out.dim.ptr, start, _INT), shape=(n,), dtype=int),
    wp.array(ptr=_offset(contacts_out.geom.ptr, start, _VEC2I), shape=(n,), dtype=wp.vec2i),
    wp.array(ptr=_offset(contacts_out.efc_address.ptr, start, k * _INT), shape=(n, k), dtype=int),
    wp.array(ptr=_offset(contacts_out.worldid.ptr, start, _INT), shape=(n,), dtype=int),
    wp.array(ptr=_offset(contacts_out.type.ptr, start, _INT), shape=(n,), dtype=int),
    wp.array(ptr=_offset(contacts_out.geomcollisionid.ptr, start, _INT), shape=(n,), dtype=int),
    wp.array(ptr=_offset(contacts_out.adhesion.ptr, start, _FLOAT), shape=(n,), dtype=float),
    wp.array(ptr=counter, shape=(1,), dtype=int),
  )


@wp.func
def shared_rows(
  quota: ContactQuota,
  worldid: int,
  naconmax_in: int,
  contacts_out: ContactRows,
):
  """world_rows without a quota: the row limit, the contact arrays themselves and ``d.nacon``."""
  return (
    naconmax_in, contacts_out.dist, contacts_out.pos, contacts_out.frame, contacts_out.includemargin,
    contacts_out.friction, contacts_out.solref, contacts_out.solreffriction, contacts_out.solimp, contacts_out.dim,
    contacts_out.geom, contacts_out.efc_address, contacts_out.worldid, contacts_out.type, contacts_out.geomcollisionid,
    contacts_out.adhesion, contacts_out.nacon,
  )


def rows(per_world: bool):
  """The rows of a kernel built per quota (call it with ``wp.static``): world_rows when
  Options.contacts_per_world > 0, else shared_rows, the contact arrays themselves."""
  return world_rows if per_world else shared_rows


@wp.func
def write_row(
  quota: ContactQuota,
  worldid: int,
  naconmax_in: int,
  id_: int,
  dist: float,
  pos: wp.vec3,
  frame: wp.mat33,
  margin: float,
  gap: float,
  condim: int,
  friction: vec5,
  solref: wp.vec2,
  solreffriction: wp.vec2,
  solimp: vec5,
  adhesion: float,
  geoms: wp.vec2i,
  pairid: wp.vec2i,
  contacts_out: ContactRows,
) -> int:
  """MuJoCo Warp's write_contact of one contact of world ``worldid`` into the rows it may write:
  without a quota the contact arrays themselves (no views made), else its world's rows."""
  if quota.per_world == 0:
    return write_contact(
      naconmax_in, id_, dist, pos, frame, margin, gap, condim, friction, solref, solreffriction, solimp, adhesion,
      geoms, pairid, worldid, contacts_out.dist, contacts_out.pos, contacts_out.frame, contacts_out.includemargin,
      contacts_out.friction, contacts_out.solref, contacts_out.solreffriction, contacts_out.solimp, contacts_out.dim,
      contacts_out.geom, contacts_out.efc_address, contacts_out.worldid, contacts_out.type,
      contacts_out.geomcollisionid, contacts_out.adhesion, contacts_out.nacon,
    )
  (limit, rows_dist, rows_pos, rows_frame, rows_includemargin, rows_friction, rows_solref, rows_solreffriction,
   rows_solimp, rows_dim, rows_geom, rows_efc_address, rows_worldid, rows_type, rows_geomcollisionid, rows_adhesion,
   rows_nacon) = world_rows(
    quota, worldid, naconmax_in, contacts_out,
  )
  return write_contact(
    limit, id_, dist, pos, frame, margin, gap, condim, friction, solref, solreffriction, solimp, adhesion, geoms,
    pairid, worldid, rows_dist, rows_pos, rows_frame, rows_includemargin, rows_friction, rows_solref,
    rows_solreffriction, rows_solimp, rows_dim, rows_geom, rows_efc_address, rows_worldid, rows_type,
    rows_geomcollisionid, rows_adhesion, rows_nacon,
  )


# --- per Data --------------------------------------------------------------------------------


@dataclasses.dataclass
class QuotaBuffers:
  """What packing the world rows needs (made with the Data's collision state)."""

  quota: ContactQuota
  world_kept: wp.array  # (nworld) contacts each world keeps: min(found, per_world)
  world_start: wp.array  # (nworld) their first row once packed
  stock_dropped: wp.array  # (1) contacts MuJoCo Warp's own writers found beyond naconmax
  nwarned: wp.array  # (1) overflow warnings printed this step


def make_buffers(nworld: int, per_world: int) -> QuotaBuffers:
  """Buffers on the current device; the per-world ones are placeholders when ``per_world`` is 0."""
  n = nworld if per_world > 0 else 1
  quota = ContactQuota()
  quota.per_world = per_world
  quota.world_ncon = wp.zeros(n, dtype=int)
  return QuotaBuffers(quota=quota, world_kept=wp.zeros(n, dtype=int), world_start=wp.zeros(n, dtype=int),
                      stock_dropped=wp.zeros(1, dtype=int), nwarned=wp.zeros(1, dtype=int))


# the contact fields the plugin's writers take (contact_outputs, in that order)
WRITTEN_CONTACT_FIELDS = (
  "dist", "pos", "frame", "includemargin", "friction", "solref", "solreffriction", "solimp", "dim", "geom",
  "efc_address", "worldid", "type", "geomcollisionid", "adhesion",
)  # fmt: skip


def contact_outputs(d) -> list:
  """The output the plugin's contact writers take: [contact_rows(d)]."""
  return [contact_rows(d)]


def _held_struct(owner, attr: str, struct, names: tuple, arrays: list):
  """The ``struct`` of ``arrays`` (its fields ``names``) kept on ``owner`` under ``attr``, made
  again when one of the arrays was replaced since (a Data's or a Model's array swapped for another)."""
  held = getattr(owner, attr, None)
  if held is None or any(a is not b for a, b in zip(held[0], arrays)):
    value = struct()
    for name, a in zip(names, arrays):
      setattr(value, name, a)
    held = (arrays, value)
    object.__setattr__(owner, attr, held)
  return held[1]


def contact_rows(d) -> ContactRows:
  """d's contact arrays and counter as one ContactRows, made once a Data."""
  return _held_struct(d, "_mjx_supportfield_contact_rows", ContactRows, WRITTEN_CONTACT_FIELDS + ("nacon",),
                      [getattr(d.contact, f) for f in WRITTEN_CONTACT_FIELDS] + [d.nacon])


MIXING_FIELDS = tuple(ContactMixing.vars)


def contact_mixing(m) -> ContactMixing:
  """m's mixing arrays as one ContactMixing, made once a Model and again when one of its arrays
  was replaced (domain randomization may swap an array for another)."""
  return _held_struct(m, "_mjx_supportfield_contact_mixing", ContactMixing, MIXING_FIELDS,
                      [getattr(m, f) for f in MIXING_FIELDS])


def check_fits(per_world: int, nworld: int, naconmax: int) -> None:
  """nworld x per_world rows must fit in naconmax."""
  if per_world * nworld > naconmax:
    raise ValueError(
      f"mjx_supportfield: Options.contacts_per_world = {per_world} gives {nworld} worlds {per_world * nworld} contact"
      f" rows, but this Data has naconmax = {naconmax}; lower contacts_per_world to at most {naconmax // nworld} or"
      " make the Data with a larger naconmax"
    )


@wp.kernel
def start_worlds(
  per_world: int,
  # Out:
  nacon: wp.array(dtype=int),
  world_ncon: wp.array(dtype=int),
  stock_dropped: wp.array(dtype=int),
  nwarned: wp.array(dtype=int),
):
  """Zeroes the world counters; MuJoCo Warp's own writers append after the world rows."""
  worldid = wp.tid()
  world_ncon[worldid] = 0
  if worldid == 0:
    nacon[0] = world_ncon.shape[0] * per_world
    stock_dropped[0] = 0
    nwarned[0] = 0


@wp.kernel
def _kept_per_world(
  per_world: int,
  naconmax: int,
  warn: bool,
  nacon: wp.array(dtype=int),
  world_ncon: wp.array(dtype=int),
  # Out:
  world_kept: wp.array(dtype=int),
  stock_dropped: wp.array(dtype=int),
  overflow: wp.array(dtype=int),
  nwarned: wp.array(dtype=int),
):
  """Each world keeps min(found, per_world) contacts; a world past its quota is flagged. Contacts
  of MuJoCo Warp's own writers beyond naconmax are counted and flag every world, as MuJoCo Warp
  flags an overflow of the shared buffer."""
  worldid = wp.tid()
  found = world_ncon[worldid]
  world_kept[worldid] = wp.min(found, per_world)
  stock = wp.max(nacon[0] - naconmax, 0)
  if worldid == 0:
    stock_dropped[0] = stock
  if found <= per_world and stock == 0:
    return
  overflow[worldid] = overflow[worldid] | int(OverflowType.NARROWPHASE)
  if warn:
    if wp.atomic_add(nwarned, 0, 1) == 0:
      if found > per_world:
        wp.printf(
          "mjx_supportfield: narrowphase overflow - %d contacts in world %d; raise Options.contacts_per_world"
          " beyond %d\n"
          "To disable the print warning: m.opt.warn_overflow &= ~mjw.OverflowType.NARROWPHASE (or = 0 for all)\n",
          found,
          worldid,
          per_world,
        )
      else:
        wp.printf(
          "mjx_supportfield: narrowphase overflow - MuJoCo Warp's own routines found %d contacts beyond naconmax %d"
          " (the rows after nworld x Options.contacts_per_world)\n"
          "To disable the print warning: m.opt.warn_overflow &= ~mjw.OverflowType.NARROWPHASE (or = 0 for all)\n",
          stock,
          naconmax,
        )


@wp.kernel
def _pack(
  per_world: int,
  naconmax: int,
  nacon: wp.array(dtype=int),
  world_kept: wp.array(dtype=int),
  world_start: wp.array(dtype=int),
  src: ContactFields,
  # Out:
  dst: ContactFields,
  efc_address: wp.array2d(dtype=int),
):
  """Row i of the copy to its packed place: the world rows that hold a contact, then the shared
  rest. A packed row need not have been written this step: its constraint rows are cleared, and
  a geom contact's flex fields too (a flex contact may have sat there)."""
  i = wp.tid()
  if i >= wp.min(nacon[0], naconmax):
    return
  nworld = world_kept.shape[0]
  nrow = nworld * per_world
  j = world_start[nworld - 1] + world_kept[nworld - 1] + i - nrow
  if i < nrow:
    worldid = i // per_world
    slot = i - worldid * per_world
    if slot >= world_kept[worldid]:
      return
    j = world_start[worldid] + slot
  contact_sort.move_row(src, i, dst, j)
  if i < nrow and dst.flex.shape[0] > 0:
    dst.flex[j] = wp.vec2i(-1)
    dst.elem[j] = wp.vec2i(-1)
    dst.vert[j] = wp.vec2i(-1)
  for k in range(efc_address.shape[1]):
    efc_address[j, k] = -1


@wp.kernel
def _packed_count(
  per_world: int,
  naconmax: int,
  world_kept: wp.array(dtype=int),
  world_start: wp.array(dtype=int),
  # In and out:
  nacon: wp.array(dtype=int),
):
  nworld = world_kept.shape[0]
  nacon[0] = world_start[nworld - 1] + world_kept[nworld - 1] + wp.min(nacon[0], naconmax) - nworld * per_world


def start(d, buf: QuotaBuffers, per_world: int) -> None:
  """Empties each world's rows before the step's writers run (per_world > 0)."""
  wp.launch(start_worlds, dim=d.nworld, inputs=[per_world],
            outputs=[d.nacon, buf.quota.world_ncon, buf.stock_dropped, buf.nwarned])


def pack(d, buf: QuotaBuffers, fields: tuple, warn: bool) -> None:
  """Packs the world rows (and the shared rest) to the front of d.contact; d.nacon counts them.
  ``fields``: contact_sort.fields_and_copy(d), the scratch the rows move through."""
  n, per_world = d.naconmax, buf.quota.per_world
  contact, copy = fields
  wp.launch(_kept_per_world, dim=d.nworld, inputs=[per_world, n, warn, d.nacon, buf.quota.world_ncon],
            outputs=[buf.world_kept, buf.stock_dropped, d.overflow, buf.nwarned])
  wp.utils.array_scan(buf.world_kept, buf.world_start, inclusive=False)
  wp.launch(contact_sort.copy_rows, dim=n, inputs=[n, d.nacon, contact], outputs=[copy])
  wp.launch(_pack, dim=n, inputs=[per_world, n, d.nacon, buf.world_kept, buf.world_start, copy],
            outputs=[contact, d.contact.efc_address])
  wp.launch(_packed_count, dim=1, inputs=[per_world, n, buf.world_kept, buf.world_start], outputs=[d.nacon])
