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
from typing import Any

import warp as wp

# contact fields the collision stage writes (efc_address is -1 and surfacevel is computed later)
FIELDS = (
  "dist", "pos", "frame", "includemargin", "friction", "solref", "solreffriction", "solimp", "dim", "geom", "flex",
  "elem", "vert", "worldid", "type", "geomcollisionid", "adhesion",
)  # fmt: skip


@dataclasses.dataclass
class SortBuffers:
  """Keys, permutation and a copy of the contact fields of one Data (made on first use)."""

  keys: wp.array  # int64, 2 x naconmax (the radix sort's scratch half included)
  index: wp.array  # int32, 2 x naconmax
  copy: dict  # field name -> array shaped like d.contact.<field> (fields sized naconmax)
  end_bit: int  # key bits the sort looks at


def make_buffers(d, ngeom: int) -> SortBuffers:
  """Buffers for sorting ``d.contact`` on its device."""
  n = d.naconmax
  device = d.contact.dist.device
  nkey = d.nworld * (ngeom + 1) * (ngeom + 1)  # the sentinel key of an unused slot
  return SortBuffers(
    keys=wp.zeros(2 * n, dtype=wp.int64, device=device),
    index=wp.zeros(2 * n, dtype=wp.int32, device=device),
    # flex, elem and vert are empty in models without flexes
    copy={f: wp.empty_like(getattr(d.contact, f)) for f in FIELDS if getattr(d.contact, f).shape[0] == n},
    end_bit=max(1, int(nkey).bit_length()),
  )


@wp.kernel(enable_backward=False)
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


@wp.kernel(enable_backward=False)
def _gather(
  naconmax: int,
  nacon: wp.array(dtype=int),
  index: wp.array(dtype=wp.int32),
  src: wp.array(dtype=Any),
  dst: wp.array(dtype=Any),
):
  """Slot i of a contact field takes slot index[i] of its copy."""
  i = wp.tid()
  if i < wp.min(nacon[0], naconmax):
    dst[i] = src[index[i]]


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
  for f, copy in buf.copy.items():
    wp.copy(copy, getattr(c, f))
    wp.launch(_gather, dim=n, inputs=[n, d.nacon, buf.index, copy], outputs=[getattr(c, f)])
