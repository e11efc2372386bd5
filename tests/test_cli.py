"""The command line: bad input gives one error line and exit code 2; compare writes its report."""

import json

import pytest
from conftest import model_path

from mjx_supportfield.cli import main


def _run(capsys, argv):
  rc = main(argv)
  out = capsys.readouterr()
  return rc, out.out, out.err


@pytest.mark.parametrize(
  "argv, needle",
  [
    (["compare", "no/such/model.xml"], "model file not found"),
    (["compare", model_path("convex_pile"), "--support-mode", "fast"], "Options.support_mode"),
    (["compare", model_path("convex_pile"), "--support-res", "2"], "Options.support_res"),
    (["compare", model_path("convex_pile"), "--samples", "0"], "--samples"),
    (["compare", model_path("convex_pile"), "--radius", "0"], "--radius"),
    (["compare", model_path("convex_pile"), "--min-depth", "nan"], "--min-depth"),
    (["bench", "no/such/model.xml"], "model file not found"),
  ],
)
def test_bad_input_is_one_error_line(capsys, argv, needle):
  rc, out, err = _run(capsys, argv)
  assert rc == 2
  lines = [x for x in err.splitlines() if x.startswith("mjx-supportfield")]
  assert len(lines) == 1 and needle in lines[0], err


def test_malformed_xml(tmp_path, capsys):
  bad = tmp_path / "bad.xml"
  bad.write_text("<mujoco><worldbody><geom type='box'")
  rc, out, err = _run(capsys, ["compare", str(bad)])
  assert rc == 2
  assert len(err.strip().splitlines()) == 1 and "XML" in err


def test_compare_report(tmp_path, capsys):
  report = tmp_path / "report.json"
  rc, out, err = _run(capsys, ["compare", model_path("mesh_on_plane"), "--steps", "10", "--samples", "2",
                               "--json", str(report), "--check"])
  assert rc == 0, err
  assert "pairs found" in out and "stock mjw" in out
  assert "legend:" in out and any(x.startswith("plugin: 0 deep points missed") for x in out.splitlines())
  data = json.loads(report.read_text())
  for impl in ("plugin", "stock"):
    summary = data["impls"][impl]["summary"]
    assert summary["pairs_reference"] > 0
    assert summary["missed_deep"] == 0
    assert summary["deep_points_reference"] > 0 and summary["contacts_outside"] == 0


def test_compare_without_collision_geoms(tmp_path, capsys):
  path = tmp_path / "ghost.xml"
  path.write_text("<mujoco><worldbody><geom type='sphere' size='.1' contype='0' conaffinity='0'/>"
                  "<body><freejoint/><geom type='box' size='.1 .1 .1' contype='0' conaffinity='0'/></body>"
                  "</worldbody></mujoco>")
  rc, out, err = _run(capsys, ["compare", str(path), "--steps", "1", "--samples", "1"])
  assert rc == 2
  lines = [x for x in err.splitlines() if x.startswith("mjx-supportfield")]
  assert len(lines) == 1 and "no collision geoms" in lines[0], err


def test_compare_check_fails_on_a_contact_off_its_shapes(tmp_path, capsys, monkeypatch):
  """--check exits 1 and names the rule a contact breaks (here a plugin contact moved 5 cm)."""
  from mjx_supportfield import compare

  real = compare.warp_contacts

  def shifted(mjm, states, nworld=None, plugin=None):
    worlds = real(mjm, states, nworld, plugin)
    if plugin is not None:
      worlds[0][0].pos = worlds[0][0].pos + [0.0, 0.0, 0.05]
    return worlds

  monkeypatch.setattr(compare, "warp_contacts", shifted)
  rc, out, err = _run(capsys, ["compare", model_path("mesh_on_plane"), "--steps", "0", "--samples", "1", "--check"])
  assert rc == 1
  assert "off their shapes" in err and "fails:" in out
