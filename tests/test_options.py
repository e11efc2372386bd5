"""Options: defaults, validation (ValueError naming the field) and from_dict."""

import dataclasses
import math

import pytest

from mjx_supportfield import Options


def test_defaults():
  o = Options()
  assert o.support_res == 180
  assert o.max_collision_pairs == 4096
  assert o.support_mode == "refined"
  assert o.sap_axis in (0, 1, 2)
  assert o.mpr_iterations >= 1
  assert 0 < o.mpr_tolerance <= 1e-2


def test_frozen():
  o = Options()
  with pytest.raises(dataclasses.FrozenInstanceError):
    o.support_res = 90


@pytest.mark.parametrize("mode", ["field", "refined", "exact"])
def test_valid_modes(mode):
  assert Options(support_mode=mode).support_mode == mode


INVALID = [
  ("support_res", 0),
  ("support_res", 3),
  ("support_res", -180),
  ("support_res", 5000),
  ("support_res", 180.0),
  ("support_res", "180"),
  ("support_res", True),
  ("warm_start", 1),
  ("multi_contact", "yes"),
  ("support_res", None),
  ("support_mode", "fast"),
  ("support_mode", "Refined"),
  ("support_mode", ""),
  ("support_mode", None),
  ("support_mode", 1),
  ("max_collision_pairs", 0),
  ("max_collision_pairs", -1),
  ("max_collision_pairs", 1.5),
  ("max_collision_pairs", "4096"),
  ("max_collision_pairs", False),
  ("mpr_iterations", 0),
  ("mpr_iterations", 2.0),
  ("mpr_tolerance", 0.0),
  ("mpr_tolerance", -1e-6),
  ("mpr_tolerance", math.nan),
  ("mpr_tolerance", math.inf),
  ("mpr_tolerance", 1.0),
  ("mpr_tolerance", "1e-6"),
  ("broadphase", "SAP"),
  ("broadphase", "grid"),
  ("broadphase", None),
  ("broadphase", 0),
  ("sap_axis", 3),
  ("sap_axis", -1),
  ("sap_axis", 0.0),
  ("hfield_mprs_per_pair", 0),
  ("hfield_mprs_per_pair", 16.0),
  ("hfield_mprs_per_pair", 5000),
  ("contacts_per_world", -1),
  ("contacts_per_world", 1 << 25),
  ("contacts_per_world", 4.0),
]


@pytest.mark.parametrize("field,value", INVALID, ids=[f"{f}={v!r}" for f, v in INVALID])
def test_invalid_value_names_field(field, value):
  with pytest.raises(ValueError, match=field):
    Options(**{field: value})
  with pytest.raises(ValueError, match=field):
    Options.from_dict({field: value})


def test_boundaries_accepted():
  Options(support_res=4, max_collision_pairs=1, mpr_iterations=1, sap_axis=2)
  Options(support_res=4096)
  Options(mpr_tolerance=1e-12)
  Options(mpr_tolerance=1e-2)
  Options(hfield_mprs_per_pair=1)
  Options(hfield_mprs_per_pair=4096)
  Options(contacts_per_world=0)
  Options(contacts_per_world=1 << 24)


def test_from_dict():
  o = Options.from_dict({"support_res": 64, "support_mode": "exact", "max_collision_pairs": 17})
  assert o == Options(support_res=64, support_mode="exact", max_collision_pairs=17)
  assert Options.from_dict({}) == Options()


@pytest.mark.parametrize("keys", [["bogus"], ["support_resolution"], ["zzz", "aaa"]])
def test_from_dict_unknown_field(keys):
  values = {"support_res": 64, **{k: 1 for k in keys}}
  with pytest.raises(ValueError) as info:
    Options.from_dict(values)
  for k in keys:
    assert k in str(info.value)


@pytest.mark.parametrize("kwargs, needle", [
  ({"foo": 1}, "'foo'"),
  ({"warmstart": False}, "did you mean 'warm_start'"),
  ({"support_res": 64, "zzz": 1, "aaa": 2}, "'aaa', 'zzz'"),
])
def test_unknown_field_is_a_value_error(kwargs, needle):
  """Options(...) and Options.from_dict raise the same ValueError, naming the field and listing the
  valid ones (a dataclass alone raises TypeError)."""
  for make in (lambda: Options(**kwargs), lambda: Options.from_dict(kwargs)):
    with pytest.raises(ValueError) as info:
      make()
    message = str(info.value)
    assert needle in message and "valid fields:" in message
    assert all(f.name in message for f in dataclasses.fields(Options))


@pytest.mark.parametrize("values", [[("support_res", 64)], "support_res=64", None])
def test_from_dict_needs_a_mapping(values):
  with pytest.raises(ValueError, match="mapping"):
    Options.from_dict(values)


def test_still_a_frozen_dataclass():
  """The check on names leaves pickling, equality, hashing, replace and the signature as they were."""
  import inspect
  import pickle

  o = Options(support_res=64, nonconvex_geoms=["bowl"])
  assert pickle.loads(pickle.dumps(o)) == o
  assert hash(o) == hash(Options(support_res=64, nonconvex_geoms=("bowl",)))
  assert o != Options()
  assert dataclasses.replace(o, sap_axis=2).sap_axis == 2
  with pytest.raises(ValueError, match="sap_axis"):
    dataclasses.replace(o, sap_axis=3)
  assert list(inspect.signature(Options).parameters) == [f.name for f in dataclasses.fields(Options)]


def test_docstring_gives_each_fields_default_and_range():
  """Each field's entry in the docstring names its default (and, for numbers, its range)."""
  doc = Options.__doc__
  starts = {f.name: doc.index(f"    {f.name}: ") for f in dataclasses.fields(Options)}
  entries = {}
  for name, start in starts.items():
    end = min((s for s in starts.values() if s > start), default=len(doc))
    entries[name] = " ".join(doc[start:end].split())
  for f in dataclasses.fields(Options):
    entry = entries[f.name]
    assert "Default" in entry or "(default)" in entry, f.name
    if f.type in ("int", "float", int, float) and f.name != "sap_axis":
      assert " to " in entry, f.name
  assert "seed" not in doc
