"""The disk cache of install's work: support fields with their proofs, and SDFs, keyed by content.

Install proves, cell by cell, which support vertex each field quad holds (tens of seconds on a
CPU for a robot's hundred meshes); the answer depends only on the hulls, the resolution asked
for, the device kind and the code that builds it. So each result is stored under a sha256 of
those (the builder's own source text included: a changed builder keys afresh, never reads a
stale entry) and read back on the next install of the same meshes.

Where: ``MJX_SUPPORTFIELD_CACHE`` when set, else ``$XDG_CACHE_HOME/mjx_supportfield``, else
``~/.cache/mjx_supportfield``; one folder a kind of entry (``fields``, ``sdf``). An entry that
cannot be read (cut short, another format) is built again and rewritten; a folder that cannot be
written costs only the build next time. Entries are written to a temporary name and renamed, so
processes installing side by side never read half a file.
"""

import hashlib
import inspect
import logging
import os
import tempfile
from typing import Iterable
from typing import Optional

import numpy as np
import warp as wp

logger = logging.getLogger("mjx_supportfield")
FORMAT = "1"  # the entries' layout; a change keys every entry afresh


def root() -> str:
  """The cache's folder (see the module docstring), following the environment at each call."""
  explicit = os.environ.get("MJX_SUPPORTFIELD_CACHE", "").strip()
  if explicit:
    return os.path.abspath(os.path.expanduser(explicit))
  base = os.environ.get("XDG_CACHE_HOME", "").strip() or os.path.join(os.path.expanduser("~"), ".cache")
  return os.path.join(os.path.abspath(base), "mjx_supportfield")


def key(parts: Iterable, code: Iterable = ()) -> str:
  """sha256 of ``parts`` (arrays by dtype, shape and bytes; anything else by its repr), of the
  source text of the modules and functions in ``code``, and of the format and Warp's version."""
  h = hashlib.sha256()
  for tag in (FORMAT, wp.__version__):
    h.update(str(tag).encode())
  for obj in code:
    h.update(inspect.getsource(obj).encode())
  for part in parts:
    if isinstance(part, np.ndarray):
      h.update(f"{part.dtype.str}{part.shape}".encode())
      h.update(np.ascontiguousarray(part).tobytes())
    else:
      h.update(repr(part).encode())
  return h.hexdigest()


def load(kind: str, digest: str) -> Optional[dict]:
  """The arrays stored under ``digest`` in folder ``kind``, or None (absent or unreadable)."""
  path = os.path.join(root(), kind, f"{digest}.npz")
  if not os.path.exists(path):
    return None
  try:
    with np.load(path, allow_pickle=False) as f:
      return {name: f[name] for name in f.files}
  except Exception:  # cut short, another format: built again and rewritten
    logger.info("cache entry %s cannot be read; building it again", path)
    return None


def store(kind: str, digest: str, arrays: dict) -> None:
  """Writes ``arrays`` under ``digest`` in folder ``kind`` (atomically; a read-only folder is
  left alone)."""
  folder = os.path.join(root(), kind)
  try:
    os.makedirs(folder, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=folder, suffix=".tmp")
    try:
      with os.fdopen(fd, "wb") as f:
        np.savez(f, **arrays)
      os.replace(tmp, os.path.join(folder, f"{digest}.npz"))
    finally:
      if os.path.exists(tmp):
        os.remove(tmp)
  except OSError:
    pass
