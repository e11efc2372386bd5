"""Tuning parameters of the plugin."""

import dataclasses
import math

SUPPORT_MODES = ("field", "refined", "exact")
NARROWPHASES = ("mpr", "gjk")
BROADPHASES = ("auto", "nxn", "sap")
# "auto" takes nxn up to this many pairs after MuJoCo's static filters, sweep-and-prune beyond
NXN_MAX_PAIRS = 16384


@dataclasses.dataclass(frozen=True)
class Options:
  """Tuning parameters of the collision plugin; defaults follow the seed documents.

  Attributes:
    support_res: directions per axis of the support field (res x res cells per mesh).
    support_mode: how a convex-mesh support query is answered: "field" (4-cell lookup),
      "refined" (field vertex, then hill-climb on the convex-hull graph: exact), or "exact"
      (exhaustive scan of the hull vertices).
    broadphase: "nxn" (every pair MuJoCo's static filters keep, one thread per world and
      pair), "sap" (sweep-and-prune: scales with the geoms, not their pairs) or "auto" (nxn
      up to NXN_MAX_PAIRS such pairs).
    max_collision_pairs: broad-phase pair budget per world; pairs beyond it are dropped,
      counted and reported through ``d.overflow`` (``OverflowType.BROADPHASE``).
    narrowphase: penetration of the convex pairs that are not analytic: "mpr" (MPR, refined
      along its normal, warm-started) or "gjk" (GJK distance, EPA for overlapping cores).
    mpr_iterations: iteration cap of each MPR (or GJK / EPA) loop.
    mpr_tolerance: MPR convergence tolerance, relative to the pair's size.
    mpr_refine: MPR reruns along the last normal (the shallowest answer wins); 0 = no reruns:
      the penetration along the centre-to-centre line (or, warm-started, along the previous
      normal). At any value an answer deeper than 0.1 x the pair's size is still checked along
      both shapes' local axes.
    sap_axis: axis (0, 1, 2) on which the sweep-and-prune projects the boxes.
    multi_contact: more contacts per MPR pair by pose perturbation (not for spheres and
      ellipsoids); analytic pairs keep MuJoCo's own multi-point routines either way.
    max_contacts_per_pair: contacts per MPR pair with multi_contact (1 to 5).
    mc_perturbation: tilt angle [rad] of the perturbed poses.
    mc_tolerance: points closer than this fraction of the smaller geom's box size are duplicates.
    mpr_to_sdf_overlap_ratio: when MPR's depth exceeds this fraction of the smaller geom's
      bounding diameter (one shape largely inside the other), the contact comes from the
      shapes' signed-distance fields if they find a shallower one; 0 turns the fallback off.
      MPR only: with narrowphase="gjk", EPA's depth is exact and the fallback is not used.
    sdf_res: cells along the longest side of a mesh hull's baked SDF.
    warm_start: MPR starts from each pair's contact normal of the previous collision call
      (kept per world and geom pair, dropped once the pair finds no contact); a warm start
      that finds no contact is retried cold.
    nonconvex_geoms: names of mesh geoms collided through their true triangles (an SDF of
      the mesh) instead of MuJoCo's convex hull; also read from the MJCF custom text
      ``mjx_supportfield.nonconvex`` (names separated by spaces).
    nonconvex_sdf_res: cells along the longest side of a non-convex mesh's baked SDF.
    hfield_mprs_per_pair: room in the terrain MPR queue per heightfield pair, on average over
      all worlds. A heightfield pair's MPRs (the triangle prisms and
      terrain points that pass the cheap tests: about 10 for a geom over a few cells, a few
      hundred over a hundred cells) run side by side from this queue; those that find it full
      run one after another in the pair's own thread: the same contacts, slower (counted in
      the collider's stats as ``hfield_mprs_unqueued``).
  """

  support_res: int = 180
  support_mode: str = "refined"
  broadphase: str = "auto"
  max_collision_pairs: int = 4096
  narrowphase: str = "mpr"
  mpr_iterations: int = 50
  mpr_tolerance: float = 1e-6
  mpr_refine: int = 4
  sap_axis: int = 0
  multi_contact: bool = True
  max_contacts_per_pair: int = 5
  mc_perturbation: float = 1e-2
  mc_tolerance: float = 1e-2
  mpr_to_sdf_overlap_ratio: float = 0.5
  sdf_res: int = 32
  warm_start: bool = True
  nonconvex_geoms: tuple = ()
  nonconvex_sdf_res: int = 64
  hfield_mprs_per_pair: int = 16

  def __post_init__(self):
    _check_int("support_res", self.support_res, 4, 4096)
    if self.support_mode not in SUPPORT_MODES:
      raise ValueError(f"Options.support_mode: {self.support_mode!r} is not one of {', '.join(SUPPORT_MODES)}")
    if self.broadphase not in BROADPHASES:
      raise ValueError(f"Options.broadphase: {self.broadphase!r} is not one of {', '.join(BROADPHASES)}")
    _check_int("max_collision_pairs", self.max_collision_pairs, 1, 1 << 24)
    if self.narrowphase not in NARROWPHASES:
      raise ValueError(f"Options.narrowphase: {self.narrowphase!r} is not one of {', '.join(NARROWPHASES)}")
    _check_int("mpr_iterations", self.mpr_iterations, 1, 10_000)
    _check_float("mpr_tolerance", self.mpr_tolerance, 1e-12, 1e-2)
    _check_int("mpr_refine", self.mpr_refine, 0, 32)
    _check_int("sap_axis", self.sap_axis, 0, 2)
    for name in ("multi_contact", "warm_start"):
      if not isinstance(getattr(self, name), bool):
        raise ValueError(f"Options.{name}: expected True or False, got {getattr(self, name)!r}")
    _check_int("max_contacts_per_pair", self.max_contacts_per_pair, 1, 5)
    _check_float("mc_perturbation", self.mc_perturbation, 1e-5, 0.2)
    _check_float("mc_tolerance", self.mc_tolerance, 0.0, 0.5)
    _check_float("mpr_to_sdf_overlap_ratio", self.mpr_to_sdf_overlap_ratio, 0.0, 100.0)
    _check_int("sdf_res", self.sdf_res, 8, 256)
    _check_int("nonconvex_sdf_res", self.nonconvex_sdf_res, 8, 512)
    _check_int("hfield_mprs_per_pair", self.hfield_mprs_per_pair, 1, 4096)
    names = self.nonconvex_geoms
    if isinstance(names, str) or not isinstance(names, (tuple, list)) or not all(isinstance(n, str) for n in names):
      raise ValueError(f"Options.nonconvex_geoms: expected a list of geom names, got {names!r}")
    object.__setattr__(self, "nonconvex_geoms", tuple(names))

  @classmethod
  def from_dict(cls, values: dict) -> "Options":
    """Builds Options from a mapping; an unknown key raises ValueError naming it."""
    known = {f.name for f in dataclasses.fields(cls)}
    unknown = sorted(set(values) - known)
    if unknown:
      raise ValueError(f"Options: unknown field(s) {', '.join(unknown)}; known fields: {', '.join(sorted(known))}")
    return cls(**values)


def _check_int(name, value, lo, hi):
  if isinstance(value, bool) or not isinstance(value, int):
    raise ValueError(f"Options.{name}: expected an integer, got {value!r}")
  if not lo <= value <= hi:
    raise ValueError(f"Options.{name}: {value} is outside [{lo}, {hi}]")


def _check_float(name, value, lo, hi):
  if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
    raise ValueError(f"Options.{name}: expected a finite number, got {value!r}")
  if not lo <= value <= hi:
    raise ValueError(f"Options.{name}: {value} is outside [{lo}, {hi}]")
