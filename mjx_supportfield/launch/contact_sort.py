"""Deterministic contact order (``m.opt.deterministic & mjw.DeterminismType.CONTACTS``).

Contacts are appended with atomics, so on a GPU their order in ``d.contact`` changes from run
to run. With MuJoCo Warp's CONTACTS determinism bit set, the collision stage ends with a stable
radix sort by (world, geom[0], geom[1]). Every geom pair's contacts come from one thread, which
appends them in order, so the sorted order is the same on every run. Flex contacts (geom -1)
keep the order of their writers.

The sort covers all ``naconmax`` slots (a size the host knows, so the step stays capturable in a
CUDA graph); unused slots get a key past every real one and stay at the end.
"""

import dataclasses
from typing import Optional

import warp as wp
from mujoco_warp._src.types import vec5

from mjx_supportfield.types import MODULE_OPTIONS

wp.set_module_options(MODULE_OPTIONS)

# contact fields the collision stage writes (efc_address is -1 and surfacevel is computed later)
FIELDS = (
  "dist", "pos", "frame", "includemargin", "friction", "solref", "solreffriction", "solimp", "dim", "geom", "flex",
  "elem", "vert", "worldid", "type", "geomcollisionid", "adhesion",
)  # fmt: skip


@wp.struct
class ContactFields:
  """The fields of FIELDS, as arrays (flex, elem and vert are empty in models without flexes).

  One typed kernel moves them all: Warp 1.19 replays a CPU graph's launches of one generic
  kernel with the function of its last captured overload, so a generic per-field copy is
  wrong under capture there.
  """

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
  flex: wp.array(dtype=wp.vec2i)
  elem: wp.array(dtype=wp.vec2i)
  vert: wp.array(dtype=wp.vec2i)
  worldid: wp.array(dtype=int)
  type: wp.array(dtype=int)
  geomcollisionid: wp.array(dtype=int)
  adhesion: wp.array(dtype=float)


def host_contacts(d) -> dict:
  """Host copies of the FIELDS d.contact holds (flex fields only in models with flexes), first
  min(nacon, naconmax) rows: for comparing contacts bit for bit."""
  n = min(int(d.nacon.numpy()[0]), d.naconmax)
  return {f: getattr(d.contact, f).numpy()[:n].copy() for f in FIELDS if getattr(d.contact, f).shape[0] == d.naconmax}


def contact_fields(arrays: dict) -> ContactFields:
  """A ContactFields over the given arrays (field name -> array)."""
  out = ContactFields()
  for f in FIELDS:
    setattr(out, f, arrays[f])
  return out


@dataclasses.dataclass
class SortBuffers:
  """Keys, permutation and a copy of the contact fields of one Data (made on first use)."""

  keys: wp.array  # int64, 2 x naconmax (the radix sort's scratch half included)
  index: wp.array  # int32, 2 x naconmax
  contact: ContactFields  # d.contact's fields
  copy: ContactFields  # a copy of them, shaped alike
  end_bit: int  # key bits the sort looks at


def fields_and_copy(d) -> tuple[ContactFields, ContactFields]:
  """``d.contact``'s fields, and a copy shaped alike: the scratch rows move through when they are
  reordered (sorted here, packed by contact_quota), one per Data."""
  fields = {f: getattr(d.contact, f) for f in FIELDS}
  return contact_fields(fields), contact_fields({f: wp.empty_like(a) for f, a in fields.items()})


def make_buffers(d, ngeom: int, fields: Optional[tuple] = None) -> SortBuffers:
  """Buffers for sorting ``d.contact`` on its device; ``fields``: fields_and_copy(d), if made already."""
  n = d.naconmax
  device = d.contact.dist.device
  nkey = d.nworld * (ngeom + 1) * (ngeom + 1)  # the sentinel key of an unused slot
  contact, copy = fields or fields_and_copy(d)
  return SortBuffers(
    keys=wp.zeros(2 * n, dtype=wp.int64, device=device),
    index=wp.zeros(2 * n, dtype=wp.int32, device=device),
    contact=contact,
    copy=copy,
    end_bit=max(1, int(nkey).bit_length()),
  )


@wp.kernel
def _sort_keys(
  ngeom1: int,
  nkey: wp.int64,
  naconmax: int,
  nacon: wp.array(dtype=int),
  worldid: wp.array(dtype=int),
  geom: wp.array(dtype=wp.vec2i),
  keys_out: wp.array(dtype=wp.int64),
  index_out: wp.array(dtype=wp.int32),
):
  i = wp.tid()
  index_out[i] = wp.int32(i)
  if i >= wp.min(nacon[0], naconmax):
    keys_out[i] = nkey
    return
  g = geom[i]
  n = wp.int64(ngeom1)
  keys_out[i] = (wp.int64(worldid[i]) * n + wp.int64(g[0] + 1)) * n + wp.int64(g[1] + 1)


@wp.func
def move_row(src: ContactFields, i: int, dst: ContactFields, j: int):
  """dst[j] = src[i] for every field."""
  dst.dist[j] = src.dist[i]
  dst.pos[j] = src.pos[i]
  dst.frame[j] = src.frame[i]
  dst.includemargin[j] = src.includemargin[i]
  dst.friction[j] = src.friction[i]
  dst.solref[j] = src.solref[i]
  dst.solreffriction[j] = src.solreffriction[i]
  dst.solimp[j] = src.solimp[i]
  dst.dim[j] = src.dim[i]
  dst.geom[j] = src.geom[i]
  if src.flex.shape[0] > 0:
    dst.flex[j] = src.flex[i]
    dst.elem[j] = src.elem[i]
    dst.vert[j] = src.vert[i]
  dst.worldid[j] = src.worldid[i]
  dst.type[j] = src.type[i]
  dst.geomcollisionid[j] = src.geomcollisionid[i]
  dst.adhesion[j] = src.adhesion[i]


@wp.kernel
def copy_rows(naconmax: int, nacon: wp.array(dtype=int), src: ContactFields, dst: ContactFields):
  i = wp.tid()
  if i < wp.min(nacon[0], naconmax):
    move_row(src, i, dst, i)


@wp.kernel
def _gather(naconmax: int, nacon: wp.array(dtype=int), index: wp.array(dtype=wp.int32), src: ContactFields,
            dst: ContactFields):
  """Slot i of every contact field takes slot index[i] of the copy."""
  i = wp.tid()
  if i < wp.min(nacon[0], naconmax):
    move_row(src, index[i], dst, i)


def sort_contacts(d, buf: SortBuffers, ngeom: int) -> None:
  """Stable sort of d.contact[:nacon] by (world, geom[0], geom[1]); no host reads."""
  n = d.naconmax
  if n == 0:
    return
  c = d.contact
  nkey = d.nworld * (ngeom + 1) * (ngeom + 1)
  wp.launch(_sort_keys, dim=n, inputs=[ngeom + 1, wp.int64(nkey), n, d.nacon, c.worldid, c.geom],
            outputs=[buf.keys, buf.index])
  wp.utils.radix_sort_pairs(buf.keys, buf.index, n, end_bit=buf.end_bit)
  wp.launch(copy_rows, dim=n, inputs=[n, d.nacon, buf.contact], outputs=[buf.copy])
  wp.launch(_gather, dim=n, inputs=[n, d.nacon, buf.index, buf.copy], outputs=[buf.contact])
