"""mjx_supportfield: a support-field collision stage for MuJoCo Warp.

Typical use::

  mjm = mujoco.MjModel.from_xml_path("scene.xml")
  m = mjw.put_model(mjm)
  d = mjw.make_data(mjm, nworld=1024)
  mjx_supportfield.install(mjm, m)
  mjw.step(m, d)  # collision now runs through the plugin
"""

from mjx_supportfield.install import collision
from mjx_supportfield.install import get_collider
from mjx_supportfield.install import install
from mjx_supportfield.install import uninstall
from mjx_supportfield.options import Options

__all__ = ["Options", "install", "uninstall", "collision", "get_collider"]
__version__ = "0.1.0"
