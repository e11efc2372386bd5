"""Builds the pack of prebuilt kernel modules that ships in the wheel (launch/prebuilt.py).

  python benchmarks/prebuild.py [--targets cpu,sm80,sm90,sm100,sm120] [--out mjx_supportfield/prebuilt]
                                [--jobs 2] [MODEL.xml ...]

Steps the models (default: the suite's mesh pile, layered primitives and terrain, the terrain
robots, aloha_pot and a non-convex scene) on the CPU with the plugin's default options, so that
every module of the plugin they use is loaded, then compiles each of those modules for each
target ahead of time (``wp.compile_aot_module``: NVRTC for the GPU architectures, which needs no
GPU; LLVM for the CPU, without ``-march=native``) and writes its binaries and metadata into
``OUT/warp-<version>/<module id>/`` (binaries xz-compressed), with ``MANIFEST.json`` (targets, modules, bytes). Folders of
modules this build did not make are removed: the pack holds one version of the code.

A GPU architecture covers the later minor versions of its major (sm80 serves sm86 and sm89).
Modules that a kernel factory makes for one model's facts (a broad phase for its filters, the
analytic kernel for its pair types) are in the pack for these models only; others compile at
first use as before. Building every target takes a while on few cores: the largest modules
take minutes each with NVRTC.
"""

import argparse
import datetime
import json
import lzma
import os
import shutil
import subprocess
import sys
import tempfile
import time
from concurrent.futures import ThreadPoolExecutor

import mujoco
import mujoco_warp as mjw
import warp as wp
from mujoco_warp._src.types import BlockDim

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(HERE)
sys.path.insert(0, ROOT)

from mjx_supportfield.driver import install  # noqa: E402
from mjx_supportfield.launch.prebuilt import PACKAGE_PACK  # noqa: E402
from mjx_supportfield.launch.prebuilt import is_plugin_module  # noqa: E402
from mjx_supportfield.options import Options  # noqa: E402

MJW_DATA = os.path.join(os.path.dirname(mjw.__file__), "test_data")
DEFAULT_MODELS = [os.path.join(HERE, "scenes", s) for s in ("pile_32_128.xml", "primitives_layers_48.xml",
                                                            "terrain_32.xml", "pile_256_128.xml")] + [
  os.path.join(ROOT, "models", "real", "quadruped_rough.xml"), os.path.join(ROOT, "models", "real",
                                                                             "humanoid_rough.xml"),
  os.path.join(ROOT, "models", "nonconvex.xml"), os.path.join(ROOT, "models", "terrain.xml"),
  os.path.join(ROOT, "models", "convex_pile.xml"), os.path.join(MJW_DATA, "aloha_pot", "scene.xml")]


def load_modules(paths: list[str]) -> list:
  """Steps each model on the CPU with the plugin (2 worlds, 3 steps, then a masked reset: RL
  frameworks reset some worlds each step) and returns the plugin's Warp modules now loaded.
  Install's disk cache starts empty, so that install's own kernels (support fields, SDFs) run and
  load too."""
  from warp._src.context import user_modules

  os.environ["MJX_SUPPORTFIELD_CACHE"] = tempfile.mkdtemp(prefix="prebuild_install_")
  if not all(os.path.exists(path) for path in paths):  # the larger benchmark scenes are written, not committed
    sys.path.insert(0, HERE)
    import make_scenes

    make_scenes.main()
  with wp.ScopedDevice("cpu"):
    for path in paths:
      t = time.perf_counter()
      mjm = mujoco.MjModel.from_xml_path(path)
      m = mjw.put_model(mjm)
      install(mjm, m, Options())
      d = mjw.make_data(mjm, nworld=2, nconmax=512, njmax=4096)
      for _ in range(3):
        mjw.step(m, d)
      mjw.reset_data(m, d, reset=wp.array([True, False], dtype=bool))
      print(f"{os.path.relpath(path, ROOT)}: stepped in {time.perf_counter() - t:.0f} s", flush=True)
  return [m for m in list(user_modules.values()) if m.execs and is_plugin_module(m)]


def block_dims(module, target: str) -> list:
  """The block sizes the module is launched with on ``target``, each a variant Warp hashes apart:
  1 on the CPU; on a GPU Warp's default, and MuJoCo Warp's nxn block for the nxn broad phase's
  kernel (broadphase._grid_of)."""
  if target == "cpu":
    return [1]
  dims = [module.options["block_dim"]]
  if any(k.key.startswith("listed_pairs_kernel") for k in module.kernels.values()):
    dims.append(BlockDim().nxn_broadphase)
  return dims


def build(module, target: str, block_dim: int, out: str) -> dict:
  """Compiles ``module``'s ``block_dim`` variant for ``target`` ("cpu" or "smNN"), as Warp compiles
  it before a launch, and files its binary and metadata under ``out``; returns {file: bytes}."""
  module.get_module_hash(block_dim)  # resolves the variant's options
  options = module.resolved_options[block_dim]
  ident = module.get_module_identifier(block_dim)
  cpu = wp.get_device("cpu")
  cached = os.path.join(wp.config.kernel_cache_dir, ident)
  folder = os.path.join(out, ident)
  binary = (module._get_compile_output_name(cpu, block_dim=block_dim) if target == "cpu" else
            module._get_compile_output_name(None, output_arch=int(target[2:]), use_ptx=False, block_dim=block_dim))
  done = [os.path.join(folder, n) for n in (binary + ".xz", module._get_meta_name(block_dim))]
  if all(os.path.exists(p) for p in done):  # this code's binary is in the pack already
    return {os.path.basename(p): os.path.getsize(p) for p in done}
  with tempfile.TemporaryDirectory() as tmp:
    source = tmp
    if target == "cpu" and all(os.path.exists(os.path.join(cached, n)) for n in (
        module._get_compile_output_name(cpu, block_dim=block_dim), module._get_meta_name(block_dim))):
      source = cached  # stepping the models built it on the CPU just now, with the same options
    elif target == "cpu":
      module._compile(cpu, tmp, options=options)
    else:
      module._compile(None, tmp, output_arch=int(target[2:]), use_ptx=False, options=options)
    os.makedirs(folder, exist_ok=True)
    files = {}
    for name in os.listdir(source):
      if name.endswith(".meta"):
        shutil.copyfile(os.path.join(source, name), os.path.join(folder, name))
      elif name.endswith((".o", ".cubin")):
        with open(os.path.join(source, name), "rb") as f, open(os.path.join(folder, name + ".xz"), "wb") as g:
          g.write(lzma.compress(f.read(), preset=9 | lzma.PRESET_EXTREME))
        name += ".xz"
      else:
        continue
      files[name] = os.path.getsize(os.path.join(folder, name))
    return files


def main():
  p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
  p.add_argument("models", nargs="*")
  p.add_argument("--targets", default="cpu,sm80,sm90,sm100,sm120")
  p.add_argument("--out", default=PACKAGE_PACK)
  p.add_argument("--jobs", type=int, default=os.cpu_count() or 1)
  args = p.parse_args()
  wp.config.log_level = wp.LOG_WARNING
  wp.init()
  targets = args.targets.split(",")
  bad = [t for t in targets if t != "cpu" and not (t.startswith("sm") and t[2:].isdigit())]
  if bad:
    p.error(f"--targets: {bad[0]!r} is not cpu or smNN")
  modules = load_modules(args.models or DEFAULT_MODELS)
  out = os.path.join(args.out, f"warp-{wp.__version__}")
  os.makedirs(out, exist_ok=True)
  jobs = [(m, target, b) for target in targets for m in modules for b in block_dims(m, target)]
  # every variant of these modules (the CPU's and the GPUs'): a build of some targets keeps the others'
  keep = {m.get_module_identifier(b): m.name for m in modules for t in ("cpu", "sm90") for b in block_dims(m, t)}
  for stale in set(os.listdir(out)) - set(keep) - {"MANIFEST.json"}:
    shutil.rmtree(os.path.join(out, stale), ignore_errors=True)
  jobs.sort(key=lambda job: -len(job[0].kernels))  # the big modules first: the pool ends with small ones

  def run(job):
    module, target, block_dim = job
    s = time.perf_counter()
    files = build(module, target, block_dim, out)
    print(f"  {module.name} {target}: {time.perf_counter() - s:.0f} s, {sum(files.values()) / 1e6:.2f} MB", flush=True)

  with ThreadPoolExecutor(max_workers=args.jobs) as pool:
    list(pool.map(run, jobs))
  write_manifest(out, {ident: name for ident, name in keep.items() if os.path.isdir(os.path.join(out, ident))})


def write_manifest(out: str, names: dict) -> None:
  """MANIFEST.json of the pack folder ``out``: what it holds now (this build's targets and those
  an earlier build for the same code added), by module, with the code's commit."""
  manifest = {}
  for ident in sorted(names):
    folder = os.path.join(out, ident)
    files = {f: os.path.getsize(os.path.join(folder, f)) for f in sorted(os.listdir(folder))}
    manifest[ident] = {"module": names[ident], "files": files}
  targets = sorted({f.removesuffix(".xz").rsplit(".", 2)[-2] for e in manifest.values() for f in e["files"]
                    if not f.endswith(".meta")})
  commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=ROOT, capture_output=True, text=True).stdout
  total = sum(sum(e["files"].values()) for e in manifest.values())
  with open(os.path.join(out, "MANIFEST.json"), "w") as f:
    json.dump({"warp": wp.__version__, "targets": targets, "built": datetime.date.today().isoformat(),
               "code": commit.strip(), "bytes": total, "modules": manifest}, f, indent=1, sort_keys=True)
  print(f"{len(manifest)} modules, targets {', '.join(targets)}: {total / 1e6:.1f} MB in {out}")


if __name__ == "__main__":
  main()
