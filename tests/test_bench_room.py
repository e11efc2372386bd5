"""bench gives both implementations the same room and never times one that overflowed it."""

from conftest import model_path
from mujoco_warp._src.types import OverflowType

from mjx_supportfield.tools import bench

_PAIRS = int(OverflowType.BROADPHASE)


def _fake_impl(overflow_below: dict, calls: list):
  """A stand-in for bench.time_impl: overflows (for the implementations named in
  ``overflow_below``) while the room is under the given nconmax."""

  def impl(mjm, mjd, scene, nworld, name, ncon, launches, options):
    calls.append((name, ncon))
    bits = _PAIRS if ncon < overflow_below.get(name, 0) else 0
    rows = [bench.Row(scene, nworld, name, stage, 1.0, 1.0, nconmax=ncon, overflow=bits) for stage in ("collision", "step")]
    return rows[0], rows[1], bits

  return impl


def test_room_doubles_for_both_until_neither_overflows(monkeypatch, capsys):
  calls = []
  monkeypatch.setattr(bench, "time_impl", _fake_impl({"stock": 100}, calls))
  rows = bench.bench_scene(model_path("convex_pile"), [4], 1, 5, None, None)
  first = calls[0][1]
  rooms = [first, 2 * first, 4 * first, 8 * first]
  expected = [r for r in rooms if r < 100] + [next(r for r in rooms if r >= 100)]
  # each room timed for both implementations, the plugin too although only stock overflowed
  assert calls == [(impl, r) for r in expected for impl in ("stock", "plugin")]
  assert all(r.overflow == 0 and r.nconmax == expected[-1] for r in rows)
  assert "timing both again" in capsys.readouterr().err


def test_given_room_stays_and_overflow_is_reported(monkeypatch, capsys):
  calls = []
  monkeypatch.setattr(bench, "time_impl", _fake_impl({"plugin": 1000}, calls))
  rows = bench.bench_scene(model_path("convex_pile"), [4], 1, 5, 50, None)
  assert calls == [("stock", 50), ("plugin", 50)]
  assert {r.impl: r.overflow for r in rows} == {"stock": 0, "plugin": _PAIRS}
  err = capsys.readouterr().err
  assert "warning: convex_pile, nworld 4, plugin: overflow (broadphase) at nconmax 50" in err


def test_room_stops_growing_and_says_so(monkeypatch, capsys):
  calls = []
  monkeypatch.setattr(bench, "time_impl", _fake_impl({"stock": 10**9}, calls))
  rows = bench.bench_scene(model_path("convex_pile"), [4], 1, 5, None, None)
  assert len(calls) == 2 * bench._ROOM_ATTEMPTS
  assert [r.overflow for r in rows if r.impl == "stock"] == [_PAIRS, _PAIRS]
  assert "its timing dropped work" in capsys.readouterr().err


def test_a_timed_run_reports_no_overflow_with_room():
  """The real timing path (CPU): a scene with room reports no overflow bits of room."""
  rows = bench.bench_scene(model_path("convex_pile"), [2], 1, 5, None, None)
  assert len(rows) == 4 and all(r.overflow & bench._ROOM_BITS == 0 for r in rows)
  assert len({r.nconmax for r in rows}) == 1
