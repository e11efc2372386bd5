"""Warm start of MPR: last step's contact normal and depth of each (world, geom pair).

A per-world open-addressing hash table keyed by the geom pair. Each world counts its own
collision calls (``stamp``, since the world's last reset) and its entries carry the call that
wrote them, so nothing is ever cleared: an entry counts only when it was written by the
world's previous call, which drops a pair that left the broad phase or found no contact.

Everything here is kept per world and read only by that world's pairs: a world's warm-start
answers, and the deep-pair check's schedule that rides on them, depend on that world's own
history alone, not on which other worlds share the batch or where the world sits in it. A full
table only means cold starts for some of that world's own pairs.

Within one call, lookups and inserts run concurrently. An insert may claim only a slot whose
stamp is two or more calls old; a lookup walks past slots of the last two calls and of this
one and stops at an older (or never used) slot, which cannot lie before the entry it looks for.

Each entry also carries the call that last ran the deep-pair check on the pair
(``slot_checked``, deep_pairs.py), handed from the previous call's entry to this call's
(``lookup``, then ``insert``'s slot), so that a persistent deep pair is checked only now
and then (narrowphase.deep_verdict_holds).

This module owns the cache (``WarmCache``, ``make_cache``), its device functions, and the reset
of chosen worlds' history (``forget``: their calls, entries and the broad phase's sweep order).
"""

import dataclasses

import numpy as np
import warp as wp

from mjx_supportfield.types import MODULE_OPTIONS

wp.set_module_options(MODULE_OPTIONS)

NEVER = -(1 << 30)  # stamp of a slot never written
MAX_SLOTS = 1024  # per world: bounds the memory at nworld x 1024 x 24 bytes
_FIBONACCI = wp.constant(wp.uint32(2654435769))  # 2^32 / golden ratio


@dataclasses.dataclass
class WarmCache:
  """Device arrays of the cache of one Data."""

  stamp: wp.array  # (nworld,) each world's current collision call, counted from its last reset
  slot_stamp: wp.array2d  # (nworld, nslot) the world's call that wrote the slot
  slot_key: wp.array2d
  slot_value: wp.array2d  # vec4: normal, depth
  slot_checked: wp.array2d  # the call that last ran the deep-pair check on the entry's pair (NEVER: none)
  misses: wp.array  # (nworld,) warm-started MPRs of the current call that missed and ran cold again


def slots_per_world(npair: int) -> int:
  """Hash slots per world for at most ``npair`` warm-started pairs: a power of two >= 2 x npair."""
  return int(min(MAX_SLOTS, max(8, 1 << int(np.ceil(np.log2(max(2 * npair, 1)))))))


def make_cache(nworld: int, nslot: int) -> WarmCache:
  """An empty cache (every slot never written) on the current device."""
  return WarmCache(
    stamp=wp.zeros(nworld, dtype=int),
    slot_stamp=wp.full((nworld, nslot), NEVER, dtype=int),
    slot_key=wp.zeros((nworld, nslot), dtype=int),
    slot_value=wp.zeros((nworld, nslot), dtype=wp.vec4),
    slot_checked=wp.full((nworld, nslot), NEVER, dtype=int),
    misses=wp.zeros(nworld, dtype=int),
  )


@wp.func
def advance_stamp(stamp: wp.array(dtype=int), misses: wp.array(dtype=int), worldid: int):
  """Starts world ``worldid``'s next collision call (on the device, so it runs inside a captured graph)."""
  stamp[worldid] = stamp[worldid] + 1
  misses[worldid] = 0


@wp.func
def _home(key: int, nslot: int) -> int:
  # Fibonacci hashing spreads consecutive geom-pair keys over the table
  return int((wp.uint32(key) * _FIBONACCI) >> wp.uint32(8)) & (nslot - 1)


@wp.func
def _slot_of(slot_stamp: wp.array2d(dtype=int), slot_key: wp.array2d(dtype=int), worldid: int, key: int, stamp: int,
             live_from: int) -> int:
  """The slot of ``key``'s entry of call ``stamp``, -1 when there is none: the walk from its home
  slot passes slots of call ``live_from`` or later (an entry can lie beyond them) and stops at an
  older one."""
  nslot = slot_key.shape[1]
  s = _home(key, nslot)
  for _ in range(nslot):
    t = slot_stamp[worldid, s]
    if t < live_from:
      break
    if t == stamp and slot_key[worldid, s] == key:
      return s
    s = (s + 1) & (nslot - 1)
  return -1


@wp.func
def _previous_slot(slot_stamp: wp.array2d(dtype=int), slot_key: wp.array2d(dtype=int), now: int, worldid: int,
                   key: int) -> int:
  """The slot of ``key``'s entry of the previous call; -1 when there is none. Slots of the call
  before it may lie in the way: they were live when the previous call inserted."""
  return _slot_of(slot_stamp, slot_key, worldid, key, now - 1, now - 2)


@wp.func
def lookup(
  slot_stamp: wp.array2d(dtype=int),
  slot_key: wp.array2d(dtype=int),
  slot_value: wp.array2d(dtype=wp.vec4),
  slot_checked: wp.array2d(dtype=int),
  now: int,
  worldid: int,
  key: int,
):
  """The previous call's entry of ``key``: its (normal, depth), depth 0 when there is none, and
  the call that last ran the deep-pair check on the pair, NEVER when there is none."""
  s = _previous_slot(slot_stamp, slot_key, now, worldid, key)
  if s < 0:
    return wp.vec4(0.0), NEVER
  return slot_value[worldid, s], slot_checked[worldid, s]


@wp.func
def insert(
  slot_stamp: wp.array2d(dtype=int),
  slot_key: wp.array2d(dtype=int),
  slot_value: wp.array2d(dtype=wp.vec4),
  now: int,
  worldid: int,
  key: int,
  value: wp.vec4,
) -> int:
  """Stores this call's (normal, depth) of ``key``; returns its slot, -1 (nothing stored) when
  the table is full."""
  nslot = slot_key.shape[1]
  s = _home(key, nslot)
  for _ in range(nslot):
    t = slot_stamp[worldid, s]
    if t <= now - 2:  # free: never written, or older than the previous call
      if wp.atomic_cas(slot_stamp, worldid, s, t, now) == t:
        slot_key[worldid, s] = key
        slot_value[worldid, s] = value
        return s
    s = (s + 1) & (nslot - 1)
  return -1


@wp.func
def update(
  slot_stamp: wp.array2d(dtype=int),
  slot_key: wp.array2d(dtype=int),
  slot_value: wp.array2d(dtype=wp.vec4),
  now: int,
  worldid: int,
  key: int,
  value: wp.vec4,
) -> int:
  """Replaces the (normal, depth) of ``key`` that this call's ``insert`` stored (a later stage
  corrected it); returns its slot, -1 (nothing replaced) when the table had no room for it. The
  walk stops at a slot insert found free: the key was stored before it or not at all."""
  s = _slot_of(slot_stamp, slot_key, worldid, key, now, now - 1)
  if s >= 0:
    slot_value[worldid, s] = value
  return s


@wp.kernel
def forget_worlds(reset: wp.array(dtype=bool), sap_init: wp.array(dtype=int), stamp: wp.array(dtype=int),
                  slot_stamp: wp.array2d(dtype=int)):
  """Drops the history of the worlds ``reset`` marks: their call count, cached normals (and with
  them the deep-pair verdicts) and saved sweep-and-prune order (rebuilt from scratch on the next
  call), as for a fresh Data."""
  worldid, slot = wp.tid()
  if not reset[worldid]:
    return
  if slot == 0:
    sap_init[worldid] = 0
    stamp[worldid] = 0
  slot_stamp[worldid, slot] = NEVER


def forget(cache: WarmCache, sap_init: wp.array, reset=None) -> None:
  """Drops the history of the worlds ``reset`` (a bool array, one a world) marks, of every world
  when None: their call count, the cache's normals and the sweep-and-prune order kept in ``sap_init``."""
  if reset is None:
    sap_init.zero_()
    cache.stamp.zero_()
    cache.slot_stamp.fill_(NEVER)
  else:
    wp.launch(forget_worlds, dim=cache.slot_stamp.shape, inputs=[reset], outputs=[sap_init, cache.stamp,
              cache.slot_stamp], device=sap_init.device)
