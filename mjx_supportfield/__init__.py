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

from mjx_supportfield.options import Options

__version__ = "0.1.0"

# The public face, re-exported from where it lives. Warp and MuJoCo Warp take seconds to import, so
# the names that need them are imported on first use: ``import mjx_supportfield`` (and
# ``mjx-supportfield --help``) stays fast.
_LAZY = {
  "install": "mjx_supportfield.driver",
  "uninstall": "mjx_supportfield.driver",
  "collision": "mjx_supportfield.driver",
  "get_collider": "mjx_supportfield.driver",
  "Collider": "mjx_supportfield.collider",
  "CollisionStats": "mjx_supportfield.stats",
}

__all__ = ["Options", "install", "uninstall", "collision", "get_collider", "Collider", "CollisionStats",
           "__version__"]


def __getattr__(name):
  if name in _LAZY:
    value = getattr(importlib.import_module(_LAZY[name]), name)
    globals()[name] = value
    return value
  # a subpackage or module (mjx_supportfield.stages, ...): loaded on first access
  if not name.startswith("_") and importlib.util.find_spec(f"{__name__}.{name}") is not None:
    return importlib.import_module(f"{__name__}.{name}")
  raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def __dir__():
  return sorted(set(globals()) | set(_LAZY))
