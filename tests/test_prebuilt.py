"""Prebuilt kernel modules (launch/prebuilt.py): a pack's binary is loaded instead of compiled,
only for exactly the module it was built from, and gives the contacts a fresh build gives."""

import json
import logging
import lzma
import os
import subprocess
import sys

import numpy as np
import pytest
import warp as wp

from mjx_supportfield.launch import prebuilt
from mjx_supportfield.types import UNIQUE_MODULE_OPTIONS

pytestmark = pytest.mark.cpu_only("CPU binaries: on a GPU, benchmarks/first_step.py counts the modules the pack serves")


def _kernel(offset: float):
  @wp.kernel(module="unique", module_options=UNIQUE_MODULE_OPTIONS, enable_backward=False)
  def add_offset(a: wp.array(dtype=float)):
    a[wp.tid()] = a[wp.tid()] + wp.static(offset)

  return add_offset


def _build_for_cpu(module, folder) -> str:
  """Compiles ``module`` as a CPU launch loads it (block size 1) into ``folder``, as
  benchmarks/prebuild.py does; returns its id."""
  module.get_module_hash(1)
  module._compile(wp.get_device("cpu"), str(folder), options=module.resolved_options[1])
  return module.get_module_identifier(1)


def _pack_from(folders: dict, root) -> str:
  """A pack holding the CPU binary (compressed, as packs hold them) and metadata of each module:
  {module id: folder they are in}."""
  for ident, source in folders.items():
    target = root / f"warp-{wp.__version__}" / ident
    target.mkdir(parents=True)
    for name in os.listdir(source):
      if name.endswith(".meta"):
        (target / name).write_bytes((source / name).read_bytes())
      elif name.endswith(".o"):
        (target / (name + ".xz")).write_bytes(lzma.compress((source / name).read_bytes()))
  return str(root)


@pytest.fixture
def empty_cache(tmp_path, monkeypatch):
  """An empty kernel cache, and the test's own kernels taken for the plugin's (packs serve only
  the plugin's modules)."""
  cache = tmp_path / "kernels"
  cache.mkdir()
  monkeypatch.setattr(wp.config, "kernel_cache_dir", str(cache))
  monkeypatch.setattr(prebuilt, "is_plugin_module", lambda module: True)
  return cache


def test_a_packed_module_loads_without_compiling(tmp_path, empty_cache, monkeypatch):
  kernel = _kernel(2.0)
  module = kernel.module
  ident = _build_for_cpu(module, tmp_path / "aot")
  monkeypatch.setenv(prebuilt.ENV, _pack_from({ident: tmp_path / "aot"}, tmp_path / "pack"))
  module.unload()
  assert prebuilt.place(module, "cpu", 1)
  a = wp.ones(4, dtype=float, device="cpu")
  wp.launch(kernel, dim=4, inputs=[a], device="cpu")
  np.testing.assert_array_equal(a.numpy(), 3.0)
  assert os.listdir(empty_cache) == [ident], "Warp loaded another variant"
  placed = os.listdir(empty_cache / ident)
  assert not [f for f in placed if f.endswith(".cpp")], f"Warp compiled it: {placed}"


def test_a_changed_module_misses_the_pack(tmp_path, empty_cache, monkeypatch):
  """A pack built from one kernel's code serves no other: another constant is another hash."""
  built, changed = _kernel(3.0), _kernel(4.0)
  monkeypatch.setenv(prebuilt.ENV, _pack_from({_build_for_cpu(built.module, tmp_path / "aot"): tmp_path / "aot"},
                                              tmp_path / "pack"))
  assert changed.module.get_module_identifier(1) != built.module.get_module_identifier(1)
  assert not prebuilt.place(changed.module, "cpu", 1)
  a = wp.zeros(2, dtype=float, device="cpu")
  wp.launch(changed, dim=2, inputs=[a], device="cpu")  # compiled as usual
  np.testing.assert_array_equal(a.numpy(), 4.0)


def test_an_unreadable_pack_file_falls_back_to_compiling(tmp_path, empty_cache, monkeypatch, caplog):
  """A pack file that cannot be read (cut short) is noted once and the module compiles as usual."""
  kernel = _kernel(7.0)
  module = kernel.module
  pack = _pack_from({_build_for_cpu(module, tmp_path / "aot"): tmp_path / "aot"}, tmp_path / "pack")
  for f in (tmp_path / "pack").rglob("*.xz"):
    f.write_bytes(f.read_bytes()[:20])  # cut short
  monkeypatch.setenv(prebuilt.ENV, pack)
  monkeypatch.setattr(prebuilt, "_said", set())
  module.unload()
  with caplog.at_level(logging.WARNING, logger="mjx_supportfield"):
    assert not prebuilt.place(module, "cpu", 1)
  assert any("could not place module" in r.getMessage() for r in caplog.records)
  a = wp.zeros(2, dtype=float, device="cpu")
  wp.launch(kernel, dim=2, inputs=[a], device="cpu")
  np.testing.assert_array_equal(a.numpy(), 7.0)


def test_packs_can_be_turned_off(monkeypatch, tmp_path):
  monkeypatch.setenv(prebuilt.ENV, str(tmp_path))
  assert prebuilt.pack_roots() == [str(tmp_path), prebuilt.PACKAGE_PACK]
  monkeypatch.setenv(prebuilt.ENV, "off")
  assert prebuilt.pack_roots() == []


def test_a_device_no_pack_fits_is_named_once(tmp_path, empty_cache, monkeypatch, caplog):
  """Where the packs hold no binary of the device's target, the plugin says so once, naming the
  target and what the packs hold, and Warp compiles as usual."""
  folder = tmp_path / "pack" / f"warp-{wp.__version__}" / "wp_other_module_0000000"
  folder.mkdir(parents=True)
  (folder / "wp_other_module_0000000.sm90.cubin.xz").write_bytes(b"")
  monkeypatch.setattr(prebuilt, "PACKAGE_PACK", str(tmp_path / "pack"))
  monkeypatch.setattr(prebuilt, "_said", set())
  monkeypatch.delenv(prebuilt.ENV, raising=False)
  kernel = _kernel(5.0)
  with caplog.at_level(logging.INFO, logger="mjx_supportfield"):
    assert not prebuilt.place(kernel.module, "cpu")
    assert not prebuilt.place(_kernel(6.0).module, "cpu")
  notes = [r.getMessage() for r in caplog.records if "no prebuilt kernels" in r.getMessage()]
  assert len(notes) == 1 and "the packs hold sm90" in notes[0] and "(cpu" in notes[0], notes


def test_a_gpu_takes_the_binary_of_its_major_version_below_it(tmp_path):
  for name in ("m.sm80.cubin.xz", "m.sm90.cubin.xz", "m.sm120.cubin.xz"):
    (tmp_path / name).write_bytes(b"")
  found = lambda binary: os.path.basename(prebuilt._binary_for(str(tmp_path), binary) or "")  # noqa: E731
  assert found("m.sm86.cubin") == "m.sm80.cubin.xz"
  assert found("m.sm89.cubin") == "m.sm80.cubin.xz"
  assert found("m.sm90.cubin") == "m.sm90.cubin.xz"
  assert found("m.sm100.cubin") == ""  # another major: none
  assert found("m.sm121.cubin") == "m.sm120.cubin.xz"
  assert found("m.sm75.cubin") == ""


_CHILD = """
import json, sys
import mujoco, mujoco_warp as mjw, numpy as np, warp as wp
wp.config.log_level = wp.LOG_WARNING
import mjx_supportfield
from mjx_supportfield.launch import first_use
with wp.ScopedDevice("cpu"):
  mjm = mujoco.MjModel.from_xml_path(sys.argv[1])
  m = mjw.put_model(mjm)
  mjx_supportfield.install(mjm, m)
  d = mjw.make_data(mjm, nworld=2, nconmax=256, njmax=1024)
  mjw.collision(m, d)
  n = int(d.nacon.numpy()[0])
  np.savez(sys.argv[2], **{k: getattr(d.contact, k).numpy()[:n] for k in ("dist", "pos", "frame", "geom", "worldid")})
print(json.dumps(first_use.compile_history()))
"""


def _fresh_process(model: str, root, pack: str, out) -> list:
  """The first collision of ``model`` in a new process whose kernel cache (under ``root``) is the
  test session's less the plugin's modules (linked, not copied), packs as ``pack`` says; its
  compile history, its contacts in ``out``."""
  first_step = pytest.importorskip("first_step")  # benchmarks/, on the path in conftest
  ours = first_step.plugin_module_prefixes()
  kernels = root / "warp" / wp.__version__
  kernels.mkdir(parents=True)
  source = wp.config.kernel_cache_dir
  for name in os.listdir(source):
    if not name.startswith(ours) and os.path.isdir(os.path.join(source, name)):
      (kernels / name).symlink_to(os.path.join(source, name))
  env = {**os.environ, "WARP_CACHE_PATH": str(root / "warp"), prebuilt.ENV: pack}
  run = subprocess.run([sys.executable, "-c", _CHILD, model, str(out)], env=env, capture_output=True, text=True)
  assert run.returncode == 0, run.stderr[-3000:]
  return json.loads(run.stdout.strip().splitlines()[-1])


@pytest.mark.slow
def test_the_shipped_pack_serves_a_model_as_a_fresh_build_does(tmp_path):
  """In a new process with the plugin's modules out of the kernel cache, the package's pack
  serves every plugin module of a model's first collision (none compiles), with the contacts of
  the same modules built afresh in another such process, bit for bit (the pack's CPU binaries
  were built elsewhere, without -march=native). A failure after a kernel change means the pack
  is stale: python benchmarks/prebuild.py rebuilds it."""
  if not prebuilt.version_dirs():
    pytest.fail(f"no pack for Warp {wp.__version__} in {prebuilt.PACKAGE_PACK}: python benchmarks/prebuild.py")
  model = os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))), "models", "convex_pile.xml")
  fresh = _fresh_process(model, tmp_path / "fresh", "off", tmp_path / "fresh.npz")
  packed = _fresh_process(model, tmp_path / "packed", "", tmp_path / "packed.npz")
  by = {s["stage"]: s for s in packed}
  assert by.get("the plugin's first collision", {}).get("modules", 0) == 0, f"compiled despite the pack: {packed}"
  assert sum(s.get("prebuilt", 0) for s in packed) >= 3
  assert sum(s["modules"] for s in fresh) >= 3, f"the fresh process compiled: {fresh}"
  a, b = np.load(tmp_path / "fresh.npz"), np.load(tmp_path / "packed.npz")
  assert len(a["dist"]) > 0
  for key in a.files:
    np.testing.assert_array_equal(b[key], a[key], err_msg=key)
