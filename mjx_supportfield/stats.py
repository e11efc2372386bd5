"""What ``Collider.stats(d)`` returns: the counters of the last collision, readable at any nworld.

This module owns the host-side read of the stages' counters (``collect``) and their summary.
"""

import numpy as np


class CollisionStats(dict):
  """The counters of the last collision on a Data: a dict that prints as a summary.

  Keys (the raw values, per world where the name says so):
    pairs: broad-phase pairs kept, all worlds together.
    pairs_per_world: pairs kept in each world (a list of nworld counts).
    dropped_pairs_per_world: pairs beyond ``Options.max_collision_pairs`` in each world.
    nonfinite_worlds: worlds in which a geom pose held NaN or inf (they got no pairs).
    dropped_contacts: contacts found beyond ``d.naconmax`` (all worlds together), and with
      ``Options.contacts_per_world`` beyond each world's rows.
    dropped_contacts_per_world: those beyond each world's rows (all 0 without contacts_per_world).
    warm_start_misses: pairs whose warm-started MPR missed and ran again cold.
    warm_start_misses_per_world: those in each world.
    hfield_mprs_unqueued: terrain MPRs the heightfield queue had no room for.
    deep_pairs: MPR answers deep enough to be checked along the shapes' faces (deep_pairs.py),
      those beyond their world's rows of its queue included.
    deep_pairs_unchecked: of those, the ones beyond their world's rows: they kept MPR's answer.
    deep_pairs_reused: deep answers that kept the verdict of the pair's last check instead of a
      new one (deep_pairs.py), not counted in deep_pairs; the check ran on deep_pairs minus
      deep_pairs_unchecked.
    hfield_ccd_as_mpr: prisms of boxes and meshes on a heightfield that found the MPR queue and
      the beyond queue full and ran MPR instead (a contact of the prism's deepest point, not EPA's).
    path: "plugin", or "stock" where MuJoCo Warp's own collision stage ran
      (``Options.stock_for_analytic_models``, ``stock_pair_classes``); then ``pairs`` is its pair count, the per-world
      lists are empty and the plugin's other counters 0.
    With sleeping enabled, the pair counts are those of the step's second (incremental) pass.

  ``str(stats)`` (and ``print``) gives ``summary()``: totals, and the few worlds with the most pairs
  or drops, instead of three lists of nworld numbers; ``repr`` gives the totals on one line.
  """

  @property
  def nworld(self) -> int:
    """Worlds of the Data (0 before its first collision)."""
    return len(self.get("pairs_per_world", ()))

  def summary(self, worst: int = 3) -> str:
    """Totals of each counter, with the ``worst`` worlds by pairs and by dropped pairs."""
    if self.get("path") == "stock":
      return (f"MuJoCo Warp's own collision stage (no pair of the model is left to the plugin's kernels): {self['pairs']} broad-phase"
              f" pairs, {self['dropped_contacts']} contacts dropped beyond naconmax")
    if not self.nworld:
      return "no collision has run on this Data yet"
    pairs = self["pairs_per_world"]
    dropped = self["dropped_pairs_per_world"]
    nonfinite = self["nonfinite_worlds"]
    spread = f"; most: {_worst(pairs, worst)}" if max(pairs) > min(pairs) else ""
    lines = [f"{self['pairs']} broad-phase pairs in {self.nworld} world{'s' if self.nworld > 1 else ''} "
             f"(per world: min {min(pairs)}, mean {sum(pairs) / len(pairs):.1f}, max {max(pairs)}{spread})"]
    ndropped = sum(dropped)
    if ndropped:
      nworld = sum(1 for x in dropped if x)
      lines.append(f"dropped pairs: {ndropped} in {nworld} world{'s' if nworld > 1 else ''} (most: "
                   f"{_worst(dropped, worst)}); raise Options.max_collision_pairs")
    else:
      lines.append("dropped pairs: 0")
    per_world = self.get("dropped_contacts_per_world") or [0]
    if any(per_world):
      nworld = sum(1 for x in per_world if x)
      lines.append(f"dropped contacts: {self['dropped_contacts']}, {sum(per_world)} of them in {nworld} "
                   f"world{'s' if nworld > 1 else ''} past their rows (most: {_worst(per_world, worst)}); raise "
                   "Options.contacts_per_world")
    elif self["dropped_contacts"]:
      lines.append(f"dropped contacts: {self['dropped_contacts']} beyond naconmax; make the Data with a larger "
                   "naconmax")
    else:
      lines.append("dropped contacts: 0")
    if nonfinite:
      shown = ", ".join(str(w) for w in nonfinite[:worst]) + (", ..." if len(nonfinite) > worst else "")
      lines.append(f"worlds with NaN or inf geom poses: {len(nonfinite)} ({shown}); they got no pairs")
    else:
      lines.append("worlds with NaN or inf geom poses: 0")
    misses = self.get("warm_start_misses_per_world") or [0]
    spread = f" (most: {_worst(misses, worst)})" if any(misses) else ""
    lines.append(f"warm-start misses: {self['warm_start_misses']}{spread}")
    if self.get("hfield_ccd_as_mpr"):
      lines.append(f"heightfield prisms beyond both queues (ran MPR, not GJK/EPA): {self['hfield_ccd_as_mpr']}")
    if self.get("deep_pairs_unchecked"):
      lines.append(f"deep pairs beyond their world's rows of the check's queue: {self['deep_pairs_unchecked']} of "
                   f"{self['deep_pairs']} (they kept MPR's answer)")
    if self.get("deep_pairs_reused"):
      lines.append(f"deep pairs that kept their last check's verdict: {self['deep_pairs_reused']} (checked: "
                   f"{self['deep_pairs'] - self['deep_pairs_unchecked']})")
    if self["hfield_mprs_unqueued"]:
      lines.append(f"heightfield MPRs beyond the queue: {self['hfield_mprs_unqueued']} (run one after another; "
                   "raise Options.hfield_mprs_per_pair)")
    return "\n".join(lines)

  def __str__(self) -> str:
    return self.summary()

  def __repr__(self) -> str:
    if self.get("path") == "stock":
      return f"CollisionStats(path=stock, pairs={self['pairs']}, dropped_contacts={self['dropped_contacts']})"
    if not self.nworld:
      return "CollisionStats(no collision yet)"
    totals = {
      "pairs": self["pairs"],
      "nworld": self.nworld,
      "dropped_pairs": sum(self["dropped_pairs_per_world"]),
      "dropped_contacts": self["dropped_contacts"],
      "nonfinite_worlds": len(self["nonfinite_worlds"]),
      "warm_start_misses": self["warm_start_misses"],
      "hfield_mprs_unqueued": self["hfield_mprs_unqueued"],
    }
    return f"CollisionStats({', '.join(f'{k}={v}' for k, v in totals.items())})"


# every counter at rest: before the first collision, and those the stock path leaves untouched
_NO_COUNTS = {"pairs": 0, "pairs_per_world": [], "dropped_pairs_per_world": [], "nonfinite_worlds": [],
              "dropped_contacts": 0, "dropped_contacts_per_world": [], "warm_start_misses": 0,
              "warm_start_misses_per_world": [],
              "hfield_mprs_unqueued": 0, "hfield_ccd_as_mpr": 0, "deep_pairs": 0, "deep_pairs_unchecked": 0,
              "deep_pairs_reused": 0}


def collect(c, d, st) -> CollisionStats:
  """The counters of the last collision on ``d`` from Collider ``c``'s per-Data state ``st`` (None
  before the first collision); reads the device."""
  if c.stock_path:
    return CollisionStats({**_NO_COUNTS, "path": "stock", "pairs": int(d.ncollision.numpy()[0]),
                           "dropped_contacts": max(0, int(d.nacon.numpy()[0]) - d.naconmax)})
  if st is None:
    return CollisionStats({**_NO_COUNTS, "path": "plugin"})
  # here, not at the top: CollisionStats alone needs neither the stage nor Warp
  from mjx_supportfield.stages.heightfield import COUNT_CCD_AS_MPR
  from mjx_supportfield.stages.heightfield import COUNT_UNQUEUED

  broad = st.broad
  return CollisionStats({
    "path": "plugin",
    "pairs": int(broad.npair.numpy()[0]),
    "pairs_per_world": np.minimum(broad.world_npair.numpy(), c.broad.max_pairs).tolist(),
    "dropped_pairs_per_world": broad.ndropped.numpy().tolist(),
    "nonfinite_worlds": np.nonzero(broad.nonfinite.numpy())[0].tolist(),
    **_dropped_contacts(c, d, st),
    **_warm_start_misses(c, d, st),
    # terrain MPRs that found the heightfield queue full and ran in their pair's thread
    "hfield_mprs_unqueued": int(st.hfield.count.numpy()[COUNT_UNQUEUED]),
    "hfield_ccd_as_mpr": int(st.hfield.count.numpy()[COUNT_CCD_AS_MPR]),
    **_deep_pairs(st),
  })


def _warm_start_misses(c, d, st) -> dict:
  """Warm-started MPRs that missed and ran cold again, in all and per world."""
  per_world = st.warm.misses.numpy() if c.options.warm_start else np.zeros(d.nworld, int)
  return {"warm_start_misses": int(per_world.sum()), "warm_start_misses_per_world": per_world.tolist()}


def _deep_pairs(st) -> dict:
  """MPR answers sent to the deep-pair check, those beyond their world's rows of its queue, and
  those that kept their last check's verdict."""
  sent = st.deep.world_count.numpy()
  return {"deep_pairs": int(sent.sum()), "deep_pairs_unchecked": int(np.maximum(sent - st.deep.per_world, 0).sum()),
          "deep_pairs_reused": int(st.deep.count.numpy()[1])}


def _dropped_contacts(c, d, st) -> dict:
  """Contacts found but not stored: beyond naconmax (mjw.step flags OverflowType.NARROWPHASE) or,
  with contacts_per_world, beyond a world's rows (flagged in that world)."""
  per_world = c.options.contacts_per_world
  if not per_world:
    return {"dropped_contacts": max(0, int(d.nacon.numpy()[0]) - d.naconmax),
            "dropped_contacts_per_world": [0] * d.nworld}
  q = st.quota
  per_world_dropped = np.maximum(q.quota.world_ncon.numpy() - per_world, 0)
  return {"dropped_contacts": int(per_world_dropped.sum()) + int(q.stock_dropped.numpy()[0]),
          "dropped_contacts_per_world": per_world_dropped.tolist()}


def _worst(per_world: list, count: int) -> str:
  """'world 3: 20, world 7: 18' for the ``count`` largest values (ties: lower world first)."""
  order = sorted(range(len(per_world)), key=lambda w: (-per_world[w], w))[:count]
  return ", ".join(f"world {w}: {per_world[w]}" for w in order if per_world[w]) or "none"
