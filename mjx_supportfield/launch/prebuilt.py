"""Prebuilt kernel modules: the plugin's compiled modules shipped ready to load.

Warp names a compiled module after a hash of its code and options (``wp_<module>_<hash>``) and
looks for it in its kernel cache before it compiles. A pack holds such binaries: one folder per
module, named as in Warp's cache, with each target's binary xz-compressed (``<id>.cpu<target>.o.xz``,
``<id>.sm<arch>.cubin.xz``: a third of gzip's size, unpacked in milliseconds) and the module's
metadata, under ``warp-<version>/`` of the Warp that built them. Before Warp would compile one of
the plugin's modules (first_use.py's watch sees each load from ``install`` to the first
collision), ``place`` copies the pack's binary for the device into Warp's cache, and Warp loads it
as if it had built it.

A binary is found only under the name Warp itself derives from the module's code, options and
target, so a changed kernel, another Warp version or other options miss the pack and compile as
before; the pack is never consulted for anything but an exact module. A GPU takes the pack's
binary of its own architecture or, CUDA binaries running on later minor versions of one major
(sm_80 code on sm_86 and sm_89), the nearest below it. CPU binaries are built without
``-march=native`` (types.MODULE_OPTIONS), so one fits every host of the target.

Packs: the package's ``prebuilt/`` folder (filled by ``benchmarks/prebuild.py`` before a wheel is
built) and the folders in ``MJX_SUPPORTFIELD_PREBUILT`` (``os.pathsep``-separated; a cluster's
shared folder, say); ``MJX_SUPPORTFIELD_PREBUILT=off`` ignores them all. Where no pack has a
binary for the device's target, the plugin says so once and compiles as usual.
"""

import logging
import lzma
import os
import re
import threading

import warp as wp

PACKAGE_PACK = os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))), "prebuilt")
ENV = "MJX_SUPPORTFIELD_PREBUILT"

logger = logging.getLogger("mjx_supportfield")
_lock = threading.Lock()
_said = set()  # (Warp version, target) pairs already reported as missing
_ARCH = r"sm(\d+)(\d)"  # a CUDA target's major and minor version
_CUBIN = re.compile(rf"\.{_ARCH}\.cubin$")


def is_plugin_module(module) -> bool:
  """Whether a Warp module holds the plugin's kernels: a stage's module, or one a factory made."""
  return module.name.startswith("mjx_supportfield") or any(
    k.func.__module__.startswith("mjx_supportfield") for k in module.kernels.values())


def pack_roots() -> list[str]:
  """The pack folders searched, in order: ``MJX_SUPPORTFIELD_PREBUILT``'s, then the package's;
  none with ``MJX_SUPPORTFIELD_PREBUILT=off``."""
  value = os.environ.get(ENV, "")
  if value.strip().lower() in ("off", "0", "none"):
    return []
  return [p for p in value.split(os.pathsep) if p.strip()] + [PACKAGE_PACK]


def version_dirs() -> list[str]:
  """The packs' folders for this process's Warp version that exist."""
  return [d for d in (os.path.join(root, f"warp-{wp.__version__}") for root in pack_roots()) if os.path.isdir(d)]


def place(module, device, block_dim=None) -> bool:
  """Copies ``module``'s prebuilt binary for ``device`` and its metadata into Warp's kernel cache,
  where Warp's load finds them; False where no pack holds them (Warp then compiles it), for a
  module that is not the plugin's, and where the copy fails (a cache folder that cannot be
  written, an unreadable pack file: noted once; Warp compiles as without a pack)."""
  if not wp.config.cache_kernels or not is_plugin_module(module):
    return False
  try:
    return _place(module, device, block_dim)
  except Exception as error:  # a pack must never cost more than the compile it saves
    if "failed" not in _said:
      _said.add("failed")
      logger.warning(
        "prebuilt kernels: could not place module %s (%s: %s); compiling it and any others as usual", module.name,
        type(error).__name__, error)
    return False


def _place(module, device, block_dim) -> bool:
  device = wp.get_device(device)
  block_dim = module.options["block_dim"] if block_dim is None else block_dim
  ident = module.get_module_identifier(block_dim)
  binary = module._get_compile_output_name(device, block_dim=block_dim)
  meta = module._get_meta_name(block_dim=block_dim)
  dirs = version_dirs()
  for version_dir in dirs:
    folder = os.path.join(version_dir, ident)
    source = _binary_for(folder, binary) if os.path.isdir(folder) else None
    if source and os.path.exists(os.path.join(folder, meta)):
      target = os.path.join(wp.config.kernel_cache_dir, ident)
      os.makedirs(target, exist_ok=True)
      _write(_read(source), os.path.join(target, binary))
      _write(_read(os.path.join(folder, meta)), os.path.join(target, meta))
      return True
  _say_once_if_no_target(dirs, binary, device)
  return False


def _binary_for(folder: str, binary: str):
  """The pack's file that serves as ``binary`` in ``folder`` (compressed: ``.xz``): the same name,
  or for a CUDA binary of sm_XY the one of sm_XZ with the largest Z <= Y (binary compatible
  within a major version)."""
  exact = os.path.join(folder, binary + ".xz")
  if os.path.exists(exact):
    return exact
  match = _CUBIN.search(binary)
  if match is None:
    return None
  major, minor = match.group(1), int(match.group(2))
  stem = binary[:match.start()]
  for below in range(minor - 1, -1, -1):
    candidate = os.path.join(folder, f"{stem}.sm{major}{below}.cubin.xz")
    if os.path.exists(candidate):
      return candidate
  return None


def _read(path: str) -> bytes:
  with open(path, "rb") as f:
    data = f.read()
  return lzma.decompress(data) if path.endswith(".xz") else data


def _write(data: bytes, dest: str):
  """Writes through a temporary name, so a process that loads the module meanwhile never sees
  half a file (Warp's own cache writes are atomic the same way)."""
  temp = f"{dest}.{os.getpid()}.{threading.get_ident()}.tmp"
  with open(temp, "wb") as f:
    f.write(data)
  os.replace(temp, dest)


def _target(binary: str) -> str:
  """A binary's target as a pack names it: ``cpu<hash>`` or ``sm<arch>``."""
  return binary.rsplit(".", 2)[-2]


def targets(version_dir: str) -> set:
  """The targets a pack folder holds binaries for."""
  found = set()
  for ident in os.listdir(version_dir):
    folder = os.path.join(version_dir, ident)
    if os.path.isdir(folder):
      found |= {_target(f.removesuffix(".xz")) for f in os.listdir(folder) if f.endswith((".o.xz", ".cubin.xz"))}
  return found


def _say_once_if_no_target(dirs: list, binary: str, device) -> None:
  """Notes once a process, per target, that no pack has binaries for this device and Warp
  version (a module missing from a pack that has the target is a kernel of another version, or
  one built for a model, and compiles without a note beyond first_use's)."""
  target = _target(binary)
  key = (wp.__version__, target)
  if key in _said or not pack_roots():  # none asked for: MJX_SUPPORTFIELD_PREBUILT=off
    return
  with _lock:
    if key in _said:
      return
    _said.add(key)
    held = set().union(*(targets(d) for d in dirs)) if dirs else set()
    if any(t == target or _same_major_below(t, target) for t in held):
      return
    where = (f"the packs hold {', '.join(sorted(held))}" if held else
             f"no pack for Warp {wp.__version__} in {', '.join(pack_roots())}")
    logger.info("no prebuilt kernels for %s (%s) with Warp %s: the plugin's modules compile as usual (%s)",
                device.alias, target, wp.__version__, where)


def _same_major_below(held: str, wanted: str) -> bool:
  a, b = re.fullmatch(_ARCH, held), re.fullmatch(_ARCH, wanted)
  return bool(a and b and a.group(1) == b.group(1) and int(a.group(2)) <= int(b.group(2)))
