"""The command line: bad input gives one error line and exit code 2; compare writes its report."""

import json
import os
import subprocess
import sys

import numpy as np
import pytest
from conftest import ROOT
from conftest import model_path
from conftest import on_gpu

from mjx_supportfield.tools.cli import main


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


def test_compare_reads_a_compiled_model(tmp_path, capsys, monkeypatch):
  """A model built by code and saved compiled (.mjb, mujoco.mj_saveModel; mjlab's tasks) compares
  as its MJCF does, and a bad one is one error line; Newton, which reads MJCF, refuses it."""
  import mujoco

  mjb = str(tmp_path / "mesh_on_plane.mjb")
  mujoco.mj_saveModel(mujoco.MjModel.from_xml_path(model_path("mesh_on_plane")), mjb, None)
  report = tmp_path / "report.json"
  rc, out, err = _run(capsys, ["compare", mjb, "--steps", "10", "--samples", "2", "--json", str(report)])
  assert rc == 0, err
  assert json.loads(report.read_text())["impls"]["plugin"]["summary"]["pairs_reference"] > 0
  bad = tmp_path / "bad.mjb"
  bad.write_bytes(b"not a model")
  monkeypatch.chdir(tmp_path)  # MuJoCo writes MUJOCO_LOG.TXT where it runs
  rc, out, err = _run(capsys, ["compare", str(bad)])
  assert rc == 2 and len(err.strip().splitlines()) == 1 and "bad.mjb" in err
  rc, out, err = _run(capsys, ["bench", mjb, "--newton"])
  assert rc == 2 and "--newton reads MJCF" in err


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
  from mjx_supportfield.tools import compare

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


def _run_exit(capsys, argv):
  """main() for arguments argparse refuses (it exits): the exit code and stderr."""
  with pytest.raises(SystemExit) as info:
    main(argv)
  return info.value.code, capsys.readouterr().err


def _one_error_line(err: str) -> str:
  lines = [x for x in err.splitlines() if x.strip()]
  assert len(lines) == 1, err
  assert lines[0].startswith("mjx-supportfield") and "error:" in lines[0], err
  return lines[0]


def test_directory_as_model(capsys):
  rc, out, err = _run(capsys, ["compare", os.path.dirname(model_path("convex_pile"))])
  assert rc == 2
  line = _one_error_line(err)
  assert "is a directory" in line and "convex_pile.xml" in line and "not found" not in line


@pytest.mark.parametrize("text", ["warm_start=false", "[1,2]", "", "1", "null", "{'warm_start': False}"])
def test_options_must_be_a_json_object(capsys, text):
  code, err = _run_exit(capsys, ["compare", model_path("convex_pile"), "--options", text])
  assert code == 2
  line = _one_error_line(err)
  assert "--options" in line and "JSON object" in line and '{"warm_start": false' in line


def test_options_unknown_field(capsys):
  rc, out, err = _run(capsys, ["compare", model_path("convex_pile"), "--options", '{"warmstart": false}'])
  assert rc == 2
  line = _one_error_line(err)
  assert "'warmstart'" in line and "did you mean 'warm_start'" in line


@pytest.mark.parametrize("text", ["abc", "1024,x", "0", "4,-1", "", "1.5"])
def test_bench_nworld_must_be_positive_integers(capsys, text):
  code, err = _run_exit(capsys, ["bench", model_path("convex_pile"), "--nworld", text])
  assert code == 2
  line = _one_error_line(err)
  assert "--nworld" in line and "invalid literal" not in line


@pytest.mark.parametrize("argv, needle", [
  (["--steps", "3"], "--steps must be >= 100"),
  (["--settle", "-1"], "--settle"),
  (["--nconmax", "0"], "--nconmax"),
  (["--device", "cuda:99"], "--device cuda:99"),
  (["--keyframe", "-1"], "--keyframe must be >= 0"),
  (["--keyframe", "0"], "convex_pile.xml has 0 keyframe(s)"),
])
def test_bench_bad_numbers(capsys, argv, needle):
  rc, out, err = _run(capsys, ["bench", model_path("convex_pile"), *argv])
  assert rc == 2
  assert needle in _one_error_line(err)


def test_bench_on_the_cpu(tmp_path, capsys, monkeypatch):
  """The default world counts are the CPU's (small), the output says so, and the JSON names the
  device by its model, not "gpu": "cpu"."""
  from mjx_supportfield.tools import bench

  if on_gpu():
    pytest.skip("the CPU's defaults")
  assert max(bench.CPU_WORLDS) <= 64 < min(bench.GPU_WORLDS)
  monkeypatch.setattr(bench, "CPU_WORLDS", (1, 2))  # a quick run; the output names whatever they are
  results = tmp_path / "bench.json"
  rc, out, err = _run(capsys, ["bench", model_path("mesh_on_plane"), "--settle", "5", "--json", str(results)])
  assert rc == 0, err
  assert "nworld 1,2: the default on the CPU" in out
  data = json.loads(results.read_text())
  assert "gpu" not in data and data["device"] == bench.device_description() and data["device"].startswith("CPU: ")
  assert sorted({r["nworld"] for r in data["rows"]}) == [1, 2]


def test_settled_state_from_a_keyframe():
  """bench's start: settled from the keyframe when asked (the terrain robots' qpos0 puts them in
  the ground, their keyframe on it), from qpos0 otherwise."""
  import mujoco

  from mjx_supportfield.tools import bench

  mjm = mujoco.MjModel.from_xml_path(model_path(os.path.join("real", "quadruped_rough")))
  at_key, at_qpos0 = bench.settled_state(mjm, 0, keyframe=0), bench.settled_state(mjm, 0)
  np.testing.assert_array_equal(at_key.qpos, mjm.key_qpos[0])
  np.testing.assert_array_equal(at_qpos0.qpos, mjm.qpos0)
  assert at_key.contact.dist[: at_key.ncon].min() > at_qpos0.contact.dist[: at_qpos0.ncon].min()
  with pytest.raises(ValueError, match="keyframe 1: the model has 1 keyframe"):
    bench.settled_state(mjm, 0, keyframe=1)


def test_plot_missing_file(tmp_path, capsys):
  rc, out, err = _run(capsys, ["plot", str(tmp_path / "none.json"), str(tmp_path / "out.png")])
  assert rc == 2
  assert "results file not found" in _one_error_line(err)


@pytest.mark.parametrize("content, needle", [
  ('{"model": "x.xml", "impls": {"plugin": {}}}', "compare report"),
  ("not json", "not JSON"),
  ('{"rows": [{"scene": "a"}]}', "row 0 lacks nworld, impl, stage, ms"),
  ("[1, 2]", "not a bench results file"),
])
def test_plot_not_bench_results(tmp_path, capsys, content, needle):
  path = tmp_path / "results.json"
  path.write_text(content)
  rc, out, err = _run(capsys, ["plot", str(path), str(tmp_path / "out.png")])
  assert rc == 2
  assert needle in _one_error_line(err)


def test_plot_axes_start_at_zero_and_name_the_device(tmp_path):
  pytest.importorskip("matplotlib")
  import matplotlib.pyplot as plt

  from mjx_supportfield.tools import bench

  rows = [{"scene": "s", "nworld": n, "impl": impl, "stage": stage, "ms": ms}
          for n, ms in ((1024, 5.0), (4096, 6.0)) for impl in ("stock", "plugin") for stage in ("collision", "step")]
  bench.plot(rows, str(tmp_path / "out.png"), "NVIDIA H200")
  fig = plt.gcf()
  assert all(ax.get_ylim()[0] == 0 for ax in fig.axes)
  assert "NVIDIA H200" in fig._suptitle.get_text()
  plt.close(fig)


def test_version(capsys):
  import importlib.metadata

  import mjx_supportfield

  with pytest.raises(SystemExit) as info:
    main(["--version"])
  out = capsys.readouterr().out
  assert info.value.code == 0
  try:
    expected = importlib.metadata.version("mjx_supportfield")
  except importlib.metadata.PackageNotFoundError:
    expected = mjx_supportfield.__version__
  assert out.strip() == f"mjx-supportfield {expected}"


def test_help_does_not_import_warp():
  """--help answers without importing Warp or MuJoCo Warp (seconds of imports)."""
  code = ("import sys\nfrom mjx_supportfield.tools.cli import main\n"
          "try:\n  main(['--help'])\nexcept SystemExit:\n  pass\n"
          "main_help = [m for m in ('warp', 'mujoco_warp', 'mujoco') if m in sys.modules]\n"
          "try:\n  main(['compare', '--help'])\nexcept SystemExit:\n  pass\n"
          "print('imported:', main_help + [m for m in ('warp', 'mujoco_warp') if m in sys.modules])")
  env = {**os.environ, "PYTHONPATH": ROOT + os.pathsep + os.environ.get("PYTHONPATH", "")}
  out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, check=True).stdout
  assert out.strip().endswith("imported: []"), out
