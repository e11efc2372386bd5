"""mjx_supportfield: a support-field collision stage for MuJoCo Warp.

Typical use::

  wp.config.log_level = wp.LOG_WARNING  # before Warp starts: no banner, no line per module loaded
  mjm = mujoco.MjModel.from_xml_path("scene.xml")
  m = mjw.put_model(mjm)
  d = mjw.make_data(mjm, nworld=1024)
  mjx_supportfield.install(mjm, m)
  mjw.step(m, d)  # collision now runs through the plugin
  print(mjx_supportfield.get_collider(m).stats(d))

The first use of a model compiles Warp kernels that are not in Warp's kernel cache yet (about a
minute on a CPU, minutes on a GPU); the plugin says what compiles and roughly how long on logger
``mjx_supportfield`` (``first_use``), silenced with
``logging.getLogger("mjx_supportfield").setLevel(logging.WARNING)``.
"""

import importlib
import importlib.util
import sys
import types

from mjx_supportfield.options import Options

__version__ = "0.1.0"

# Warp and MuJoCo Warp take seconds to import: the functions that need them are imported on first
# use, so that ``import mjx_supportfield`` (and ``mjx-supportfield --help``) stays fast.
_LAZY = {
  "install": "mjx_supportfield.install",
  "uninstall": "mjx_supportfield.install",
  "collision": "mjx_supportfield.install",
  "get_collider": "mjx_supportfield.install",
  "CollisionStats": "mjx_supportfield.stats",
}

__all__ = ["Options", "install", "uninstall", "collision", "get_collider", "CollisionStats", "__version__"]


def __getattr__(name):
  if name in _LAZY:
    value = getattr(importlib.import_module(_LAZY[name]), name)
    globals()[name] = value
    return value
  # a submodule (mjx_supportfield.collider, ...): importing the package used to import them all
  if not name.startswith("_") and importlib.util.find_spec(f"{__name__}.{name}") is not None:
    return importlib.import_module(f"{__name__}.{name}")
  raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def __dir__():
  return sorted(set(globals()) | set(_LAZY))


class _Package(types.ModuleType):
  """The package module: keeps the function ``install`` when its submodule is imported."""

  def __setattr__(self, name, value):
    # importing a submodule binds it on the package: ``mjx_supportfield.install`` would then be the
    # module mjx_supportfield/install.py instead of the function, as it was before lazy imports
    if name in _LAZY and isinstance(value, types.ModuleType):
      return
    super().__setattr__(name, value)


sys.modules[__name__].__class__ = _Package
