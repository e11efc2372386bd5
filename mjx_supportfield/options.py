"""Tuning parameters of the plugin."""

import collections.abc
import dataclasses
import difflib
import functools
import math

SUPPORT_MODES = ("field", "refined", "exact")
NARROWPHASES = ("mpr", "gjk")
BROADPHASES = ("auto", "nxn", "sap")
# the pair classes of Options.stock_pair_classes (stages/routing.py's PairClass)
PAIR_CLASSES = ("analytic", "primitive", "mesh", "mesh_mesh", "hfield_round", "hfield_prism")
# "auto" takes nxn up to this many pairs after MuJoCo's static filters, sweep-and-prune beyond
NXN_MAX_PAIRS = 16384


def _reject_unknown_fields(cls):
  """Makes ``cls(name=...)`` with a name that is not a field raise ValueError naming it and listing
  the fields, as ``from_dict`` does (a dataclass's own __init__ raises TypeError)."""
  init = cls.__init__

  @functools.wraps(init)
  def __init__(self, *args, **kwargs):
    unknown = sorted(set(kwargs) - _field_names(cls))
    if unknown:
      raise ValueError(_unknown_fields_message(cls, unknown))
    init(self, *args, **kwargs)

  cls.__init__ = __init__
  return cls


@_reject_unknown_fields
@dataclasses.dataclass(frozen=True)
class Options:
  """Tuning parameters of the collision plugin. The defaults suit most models; each entry says
  its default, its valid range and when to change it. An unknown field or an invalid value raises
  ValueError naming the field (``Options(...)`` and ``Options.from_dict``).

  Attributes:
    support_res: directions per axis of each convex mesh's support table (res x res cells per
      mesh; memory grows with its square). Default 180, integer 4 to 4096. Lower it to save memory
      on many large meshes; with support_mode="refined" the answer stays exact, only slower.
    support_mode: how a convex mesh's support point (its farthest vertex along a direction) is
      found. "refined" (default): the table's vertex, then a walk on the hull's vertex graph to the
      exact answer. "field": the table's 4-cell lookup only (approximate, fastest). "exact": a scan
      of every hull vertex (slow on large hulls; a reference).
    broadphase: "auto" (default): nxn up to NXN_MAX_PAIRS (16384) geom pairs after MuJoCo's static
      filters, times the ratio of the paired geoms to the moving ones (a terrain's static tiles and
      boxes raise it: broadphase.nxn_pair_limit), sweep-and-prune beyond. "nxn": every such pair,
      one thread per world and pair.
      "sap": sweep-and-prune, which scales with the geoms rather than their pairs. Force one only
      to compare them.
    max_collision_pairs: broad-phase pairs kept per world. Default 4096, integer 1 to 16777216
      (2**24). Pairs beyond it are dropped, counted (``stats(d)``) and flagged in ``d.overflow``
      (``OverflowType.BROADPHASE``); raise it when that happens, lower it to save memory (buffers
      grow with nworld x max_collision_pairs).
    narrowphase: the penetration solver of the convex pairs that have no analytic routine.
      "mpr" (default): MPR, refined along its normal and warm-started. "gjk": GJK distance, EPA
      when the shapes' cores overlap: slower, the better normal on deep mesh-mesh overlaps.
    mpr_iterations: iteration cap of each MPR (or GJK / EPA) loop. Default 50, integer 1 to
      10000. Rarely worth changing: MPR converges in far fewer on well-shaped hulls.
    mpr_tolerance: MPR convergence tolerance, relative to the pair's size. Default 1e-6, 1e-12 to
      1e-2. Larger: faster, coarser depths and normals.
    mpr_refine: MPR reruns along the last normal (the shallowest answer wins). Default 4, integer
      0 to 32. Fewer: faster, with less exact normals on curved surfaces; 0 = no reruns: the
      penetration along the centre-to-centre line (or, warm-started, along the previous normal).
      At any value an answer deeper than 0.1 x the pair's size is still checked along both
      shapes' local axes.
    sap_axis: axis (0, 1, 2: x, y, z) on which sweep-and-prune projects the boxes. Default 0. Pick
      the axis along which the geoms spread most (not the vertical for a pile or a stack).
    multi_contact: more contacts per MPR pair by tilting one shape slightly (not for spheres and
      ellipsoids, which touch in one point); analytic pairs keep MuJoCo's own multi-point
      routines either way. Default True. False: one contact per pair, faster, less stable resting
      contact of faces and edges.
    max_contacts_per_pair: contacts per MPR pair with multi_contact (``mpr_pair_contacts``), and
      the cap of the spread choice on terrain and non-convex pairs. Default 5, integer 1 to 5.
    mc_perturbation: tilt angle [rad] of the perturbed poses. Default 1e-2, 1e-5 to 0.2. Rarely
      worth changing.
    mc_tolerance: points closer than this fraction of the smaller geom's box size are duplicates.
      Default 1e-2, 0 to 0.5.
    mpr_to_sdf_overlap_ratio: when MPR's depth exceeds this fraction of the smaller geom's
      bounding diameter (one shape largely inside the other), the contact comes from the
      shapes' signed-distance fields if they find a shallower one. Default 0.5, 0 to 100; 0 turns
      the fallback off. MPR only: with narrowphase="gjk", EPA's depth is exact and the fallback is
      not used.
    sdf_res: cells along the longest side of a mesh hull's baked signed-distance field (for the
      fallback above). Default 32, integer 8 to 256. Memory and install time grow with its cube.
    warm_start: MPR starts from each pair's contact normal of the previous collision call
      (kept per world and geom pair, dropped once the pair finds no contact); a warm start
      that finds no contact is retried cold. Default True. False: every call starts cold (its
      answer then does not depend on the previous step).
    nonconvex_geoms: names of mesh geoms collided through their true triangles (an SDF of
      the mesh) instead of MuJoCo's convex hull: bowls, cups, hooks. Default () (none); also read
      from the MJCF custom text ``mjx_supportfield.nonconvex`` (names separated by spaces).
    nonconvex_sdf_res: cells along the longest side of a non-convex mesh's baked SDF. Default 64,
      integer 8 to 512. Raise it for thin walls or fine features.
    hfield_mprs_per_pair: room in the terrain MPR queue per heightfield pair of a geom other
      than a sphere or a capsule (and per 8 of those: they take MPRs only where they reach past
      the heightfield's edge), on average over all worlds. Default 64, integer 1 to 4096. A
      heightfield pair's MPRs (the triangle prisms and terrain points that pass the cheap tests:
      about 10 for a geom over a few cells, a few hundred over a hundred cells) run side by side
      from this queue; those that find it full run one after another in the pair's own thread:
      the same contacts, slower (counted in the collider's stats as ``hfield_mprs_unqueued``;
      raise it when that count is large).
    contacts_per_world: rows of ``d.contact`` each world owns. Default 0, integer 0 to 16777216
      (2**24). 0: all worlds share ``d.naconmax`` rows, first come first served, so when they
      overflow any world can lose contacts. N > 0: world w writes rows [w*N, (w+1)*N) only, and
      a world with more contacts than N loses its own (counted per world in ``stats(d)``, flagged
      in ``d.overflow`` as ``OverflowType.NARROWPHASE``), never another world's; the rows are
      then packed to the front. nworld x N must fit in naconmax; the rows beyond hold the
      contacts of MuJoCo Warp's own collision routines (SDF geoms, collision sensors, flexes),
      which stay shared. Not with sleeping enabled (install refuses it).
    stock_for_analytic_models: what collides a model that gives the plugin nothing to do: every
      geom pair one of MuJoCo's analytic pairs (no convex mesh, cylinder or ellipsoid pair left
      to MPR, no heightfield, no non-convex mesh) and few enough pairs for the nxn broad phase.
      The plugin would run MuJoCo Warp's own analytic routines on the same pairs and write the
      same contacts, bit for bit, with more launches. Default True: such a model collides
      through MuJoCo Warp's own collision stage; ``stats(d)`` then holds only its pair count
      (``path`` is "stock"), and the plugin's per-world pair budget and NaN-pose skip do not
      apply. False, ``broadphase`` other than "auto", or ``contacts_per_world`` > 0: the
      plugin's own pipeline.
    stock_pair_classes: pair classes collided by MuJoCo Warp's own narrow phase instead of the
      plugin's kernels, on the plugin's broad-phase pairs (docs/performance.md times each class
      both ways): "analytic" (MuJoCo's closed forms: plane against a geom, sphere and capsule
      pairs, box-box; through the plugin the same routines), "primitive" (other pairs of convex
      primitives: cylinders, ellipsoids), "mesh" (a convex mesh against a primitive), "mesh_mesh",
      "hfield_round" (a sphere or capsule on a heightfield: the plugin's closed form per
      triangle), "hfield_prism" (a box, cylinder, ellipsoid or convex mesh on a heightfield: the
      plugin's MPR per triangle prism). Default () (none): by docs/performance.md's cost model
      the plugin's kernels are the faster for every class but the heightfield's, where MuJoCo
      Warp's are faster and let a box and an ellipsoid sink through models/terrain.xml, which
      the plugin's prisms hold. Their contacts are MuJoCo Warp's (GJK/EPA and its
      multi-contact for the convex pairs), written after the plugin's; non-convex meshes stay
      the plugin's. A model whose every pair is routed there
      (and with nothing for the plugin's broad phase to do, as for stock_for_analytic_models)
      collides through MuJoCo Warp's own collision stage.
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
  hfield_mprs_per_pair: int = 64
  contacts_per_world: int = 0
  stock_for_analytic_models: bool = True
  stock_pair_classes: tuple = ()

  @property
  def mpr_pair_contacts(self) -> int:
    """Contacts an MPR pair may write: ``max_contacts_per_pair`` with ``multi_contact``, else 1
    (the narrow phase and the deep-pair check, which answer MPR pairs, read it here)."""
    return self.max_contacts_per_pair if self.multi_contact else 1

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
    for name in ("multi_contact", "warm_start", "stock_for_analytic_models"):
      if not isinstance(getattr(self, name), bool):
        raise ValueError(f"Options.{name}: expected True or False, got {getattr(self, name)!r}")
    _check_int("max_contacts_per_pair", self.max_contacts_per_pair, 1, 5)
    _check_float("mc_perturbation", self.mc_perturbation, 1e-5, 0.2)
    _check_float("mc_tolerance", self.mc_tolerance, 0.0, 0.5)
    _check_float("mpr_to_sdf_overlap_ratio", self.mpr_to_sdf_overlap_ratio, 0.0, 100.0)
    _check_int("sdf_res", self.sdf_res, 8, 256)
    _check_int("nonconvex_sdf_res", self.nonconvex_sdf_res, 8, 512)
    _check_int("hfield_mprs_per_pair", self.hfield_mprs_per_pair, 1, 4096)
    _check_int("contacts_per_world", self.contacts_per_world, 0, 1 << 24)
    names = self.nonconvex_geoms
    if isinstance(names, str) or not isinstance(names, (tuple, list)) or not all(isinstance(n, str) for n in names):
      raise ValueError(f"Options.nonconvex_geoms: expected a list of geom names, got {names!r}")
    object.__setattr__(self, "nonconvex_geoms", tuple(names))
    classes = self.stock_pair_classes
    if isinstance(classes, str) or not isinstance(classes, (tuple, list)):
      raise ValueError(f"Options.stock_pair_classes: expected a list of pair classes, got {classes!r}")
    unknown = [c for c in classes if c not in PAIR_CLASSES]
    if unknown:
      raise ValueError(f"Options.stock_pair_classes: {unknown[0]!r} is not one of {', '.join(PAIR_CLASSES)}")
    object.__setattr__(self, "stock_pair_classes", tuple(classes))

  @classmethod
  def from_dict(cls, values: dict) -> "Options":
    """Builds Options from a mapping; an unknown key raises ValueError naming it."""
    if not isinstance(values, collections.abc.Mapping):
      raise ValueError(f"Options.from_dict: expected a mapping of field names to values, got {type(values).__name__}")
    unknown = sorted((k for k in values if k not in _field_names(cls)), key=repr)
    if unknown:
      raise ValueError(_unknown_fields_message(cls, unknown))
    return cls(**values)


def _field_names(cls) -> set:
  return {f.name for f in dataclasses.fields(cls)}


def _unknown_fields_message(cls, unknown: list) -> str:
  known = sorted(_field_names(cls))
  hints = [f"{name!r} (did you mean {close[0]!r}?)"
           if isinstance(name, str) and (close := difflib.get_close_matches(name, known, 1)) else repr(name)
           for name in unknown]
  return (f"Options: unknown field{'s' if len(unknown) > 1 else ''} {', '.join(hints)}; valid fields: "
          f"{', '.join(known)}")


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
