"""Notes on compiling Warp kernels at first use (logger mjx_supportfield): which modules, how many,
how long; the plugin's first collision planned without side effects; the watch gone afterwards."""

import logging
import os
import random

import mujoco_warp as mjw
import numpy as np
import pytest
import warp as wp
from warp._src import context as wp_context

import mjx_supportfield as sf
from conftest import bitwise_repeatable
from conftest import load
from mjx_supportfield.launch import first_use
from mjx_supportfield.launch import prebuilt
from test_install import contact_records

LOAD = wp_context.Module.load  # Warp's own, before any watch


@pytest.fixture(autouse=True)
def no_pending_models():
  """Models other tests installed and have not stepped are not this file's: their first collisions
  go unplanned, so that the watch here reflects these tests alone."""
  first_use._watch.pending.clear()
  first_use._watch.stop()


def _notes(caplog):
  return [r.getMessage() for r in caplog.records if r.name == "mjx_supportfield"]


def test_a_module_not_in_the_cache_is_announced(tmp_path, monkeypatch, caplog):
  """A kernel Warp must build (an empty kernel cache) is named before it builds, with a summary."""
  monkeypatch.setattr(wp.config, "kernel_cache_dir", str(tmp_path))
  scale = random.random()  # in the code: a module no earlier run has loaded

  @wp.kernel(module="unique", enable_backward=False)
  def scaled(x: wp.array(dtype=float)):
    x[wp.tid()] = wp.static(scale)

  x = wp.zeros(2)
  with caplog.at_level(logging.INFO, logger="mjx_supportfield"):
    with first_use.announce_compiles("the test"):
      wp.launch(scaled, dim=2, inputs=[x])
      wp.launch(scaled, dim=2, inputs=[x])  # loaded: no second note
  notes = _notes(caplog)
  assert len(notes) == 3, notes
  assert notes[0].startswith(f"first use on {x.device.alias}: Warp compiles kernels for the test")
  assert "test_first_use.test_a_module_not_in_the_cache_is_announced.scaled" in notes[1]
  assert "1 module compiled in" in notes[2]
  last = first_use.compile_history()[-1]  # the same, for scripts
  assert last["stage"] == "the test" and last["modules"] == 1 and last["seconds"] >= 0
  assert np.allclose(x.numpy(), np.float32(scale))
  assert wp_context.Module.load is LOAD and not first_use.active


def _pretend_uncached(monkeypatch):
  """Every module counts as not cached until loaded once under the watch: the notes of a cold
  cache without building anything (and without the packs of prebuilt modules, which would
  serve them)."""
  monkeypatch.setenv(prebuilt.ENV, "off")
  noted = set()
  note = first_use._Stage.note

  def will_compile(module, device, block_dim):
    return id(module) not in noted

  def noting(self, module, device, done=False):
    noted.add(id(module))
    note(self, module, device, done)

  monkeypatch.setattr(first_use, "_will_compile", will_compile)
  monkeypatch.setattr(first_use._Stage, "note", noting)


def test_first_collision_is_planned_and_counted(monkeypatch, caplog):
  _pretend_uncached(monkeypatch)
  sim = load("convex_pile", nworld=2)
  sf.install(sim.mjm, sim.m)
  with caplog.at_level(logging.INFO, logger="mjx_supportfield"):
    mjw.collision(sim.m, sim.d)
  notes = _notes(caplog)
  header = [n for n in notes if "for the plugin's first collision" in n]
  assert len(header) == 1, notes
  count = int(header[0].split("Warp compiles ")[1].split()[0])
  assert count >= 3 and "roughly" in header[0]  # the broad phase and the narrow phase's modules at least
  assert [n.split("]")[0].strip() for n in notes if n.strip().startswith("[")][-count:] == \
    [f"[{i}/{count}" for i in range(1, count + 1)]
  assert f"{count} modules compiled in" in notes[-1]
  assert any("mjx_supportfield.stages.narrowphase" in n for n in notes)
  # built side by side before the collision runs, each noted once built
  numbered = [n for n in notes if n.strip().startswith("[")][-count:]
  assert all(n.split("]")[1].split("(")[0].strip().endswith(" built") for n in numbered), numbered
  assert ("at a time" in header[0]) == (first_use._build_workers() > 1)


def test_build_threads_follow_the_environment(monkeypatch, caplog):
  """MJX_SUPPORTFIELD_BUILD_THREADS sets the threads that build a first collision's modules; a value
  that is no integer is named in a warning and the default (a thread a core, up to 8) holds."""
  monkeypatch.setenv("MJX_SUPPORTFIELD_BUILD_THREADS", "3")
  assert first_use._build_workers() == 3
  monkeypatch.setenv("MJX_SUPPORTFIELD_BUILD_THREADS", "0")
  assert first_use._build_workers() == 1
  monkeypatch.setenv("MJX_SUPPORTFIELD_BUILD_THREADS", "many")
  with caplog.at_level(logging.WARNING, logger="mjx_supportfield"):
    assert first_use._build_workers() == max(1, min(os.cpu_count() or 1, 8))
  assert any("'many' is not an integer" in n for n in _notes(caplog))


def test_planned_first_collision_leaves_no_trace():
  """A first collision that is planned first gives bitwise the contacts (and, warm-started, the next
  ones) of one that is not."""
  runs = []
  for planned in (True, False):
    sim = load("convex_pile", nworld=2)
    collider = sf.install(sim.mjm, sim.m)
    if not planned:
      first_use.disarm(collider)
    assert first_use.active == planned
    with bitwise_repeatable(sim.m):
      mjw.collision(sim.m, sim.d)
      first = contact_records(sim.d)
      mjw.collision(sim.m, sim.d)
    runs.append((first, contact_records(sim.d), dict(collider.stats(sim.d))))
    assert not first_use.active
  assert runs[0] == runs[1] and runs[0][0]


def test_watch_ends_after_the_first_step():
  """From the second collision on, Warp's Module.load is its own again: steps pay nothing."""
  sim = load("convex_pile", nworld=1)
  collider = sf.install(sim.mjm, sim.m)
  assert first_use.active and wp_context.Module.load is not LOAD
  mjw.step(sim.m, sim.d)
  assert first_use.active  # the rest of the first step may still compile MuJoCo Warp's kernels
  mjw.step(sim.m, sim.d)
  assert not first_use.active and wp_context.Module.load is LOAD
  sim2 = load("convex_pile", nworld=1)
  sf.install(sim2.mjm, sim2.m)
  sf.uninstall(sim2.m)  # a model uninstalled before it collides does not keep the watch on
  assert not first_use.active and wp_context.Module.load is LOAD
  assert collider.stats(sim.d)["pairs"] > 0


def test_notes_reach_stderr_without_logging_configured(capsys):
  """With no handler configured, the notes go to stderr (prefixed), not to Python's last resort,
  which drops INFO."""
  root = logging.getLogger()
  saved = root.handlers[:]
  root.handlers.clear()  # pytest's capture handlers
  try:
    first_use.logger.info("a note")
  finally:
    root.handlers[:] = saved
  assert "mjx_supportfield: a note" in capsys.readouterr().err


def test_a_model_yet_to_collide_does_not_keep_the_watch(monkeypatch, caplog):
  """Another model's step ends the wrapper (launches stop paying for it) while a model installed
  later has yet to collide; that model's first collision is still planned and counted."""
  a = load("convex_pile", nworld=1)
  sf.install(a.mjm, a.m)
  mjw.step(a.m, a.d)
  b = load("convex_pile", nworld=1)
  sf.install(b.mjm, b.m)
  mjw.step(a.m, a.d)
  assert wp_context.Module.load is LOAD and first_use.active  # b is still to collide
  _pretend_uncached(monkeypatch)
  with caplog.at_level(logging.INFO, logger="mjx_supportfield"):
    mjw.step(b.m, b.d)
  assert any("for the plugin's first collision" in n for n in _notes(caplog))
  mjw.step(b.m, b.d)
  assert wp_context.Module.load is LOAD and not first_use.active
