"""Install's disk cache (geometry/disk_cache.py): support fields and their proofs read back bit for
bit, keyed by content so that other meshes build afresh, an unreadable entry rebuilt, the folder
following the environment."""

import logging
import os

import mujoco
import mujoco_warp as mjw
import numpy as np
import pytest
from conftest import model_path

from mjx_supportfield.geometry import disk_cache
from mjx_supportfield.geometry import support_field


def _fields(mjm, caplog):
  """The support fields of ``mjm``'s meshes (their arrays on the host) and install's notes."""
  caplog.clear()
  m = mjw.put_model(mjm)
  with caplog.at_level(logging.INFO, logger="mjx_supportfield"):
    ms = support_field.build_mesh_support(mjm, m.mesh_vert, 64)
  notes = [r.getMessage() for r in caplog.records if r.name == "mjx_supportfield"]
  return {name: getattr(ms, name).numpy() for name in support_field.FIELD_ARRAYS}, notes


@pytest.fixture
def cache(tmp_path, monkeypatch):
  monkeypatch.setenv("MJX_SUPPORTFIELD_CACHE", str(tmp_path))
  return tmp_path


def test_fields_from_the_cache_are_the_built_ones(cache, caplog):
  mjm = mujoco.MjModel.from_xml_path(model_path("convex_pile"))
  built, notes = _fields(mjm, caplog)
  assert any("building and proving" in n for n in notes), notes
  assert len(list((cache / "fields").iterdir())) == 1
  read, notes = _fields(mjm, caplog)
  assert any("from the cache" in n for n in notes), notes
  for name in support_field.FIELD_ARRAYS:
    np.testing.assert_array_equal(read[name], built[name], err_msg=name)


def test_other_meshes_build_afresh(cache, caplog):
  mjm = mujoco.MjModel.from_xml_path(model_path("convex_pile"))
  _fields(mjm, caplog)
  mjm.mesh_vert[:] *= 1.001  # other hulls, the same topology
  _, notes = _fields(mjm, caplog)
  assert any("building and proving" in n for n in notes), notes
  assert len(list((cache / "fields").iterdir())) == 2


def test_unreadable_entry_is_built_again(cache, caplog):
  mjm = mujoco.MjModel.from_xml_path(model_path("convex_pile"))
  built, _ = _fields(mjm, caplog)
  (entry,) = (cache / "fields").iterdir()
  entry.write_bytes(entry.read_bytes()[:100])  # cut short
  read, notes = _fields(mjm, caplog)
  assert any("cannot be read" in n for n in notes) and any("building and proving" in n for n in notes), notes
  for name in support_field.FIELD_ARRAYS:
    np.testing.assert_array_equal(read[name], built[name], err_msg=name)
  _, notes = _fields(mjm, caplog)
  assert any("from the cache" in n for n in notes), notes  # rewritten whole


def test_the_folder_follows_the_environment(monkeypatch, tmp_path):
  monkeypatch.setenv("MJX_SUPPORTFIELD_CACHE", str(tmp_path / "here"))
  assert disk_cache.root() == str(tmp_path / "here")
  monkeypatch.delenv("MJX_SUPPORTFIELD_CACHE")
  monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "xdg"))
  assert disk_cache.root() == str(tmp_path / "xdg" / "mjx_supportfield")
  monkeypatch.delenv("XDG_CACHE_HOME")
  assert disk_cache.root() == os.path.join(os.path.expanduser("~"), ".cache", "mjx_supportfield")


def test_a_changed_builder_keys_afresh():
  """The key covers the builder's code: the same parts under other code give another key."""
  parts = ("fields", np.arange(4, dtype=np.int32), 64)
  assert disk_cache.key(parts, code=(support_field,)) == disk_cache.key(parts, code=(support_field,))
  assert disk_cache.key(parts, code=(support_field,)) != disk_cache.key(parts, code=(disk_cache,))
  assert disk_cache.key(parts) != disk_cache.key(parts[:2] + (65,))


def test_an_unwritable_folder_costs_only_the_build(tmp_path, monkeypatch, caplog):
  """A cache folder that cannot be made (here: its path names a file) is no error: the fields
  are built, as without a cache."""
  blocker = tmp_path / "a_file"
  blocker.write_text("")
  monkeypatch.setenv("MJX_SUPPORTFIELD_CACHE", str(blocker / "cache"))
  mjm = mujoco.MjModel.from_xml_path(model_path("convex_pile"))
  fields, notes = _fields(mjm, caplog)
  assert any("building and proving" in n for n in notes) and fields["field"].size > 1
  _, notes = _fields(mjm, caplog)
  assert any("building and proving" in n for n in notes)
