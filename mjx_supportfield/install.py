"""Installing the plugin on a MuJoCo Warp model, and the dispatcher that routes stepping to it."""

from typing import Optional

import mujoco
import mujoco_warp as mjw
import warp as wp
from mujoco_warp._src import collision_driver

from mjx_supportfield.collider import _ATTR
from mjx_supportfield.collider import Collider
from mjx_supportfield.options import Options

_STOCK_COLLISION = collision_driver.collision


def _dispatch(m, d, awake_prev: Optional[wp.array] = None):
  """Stand-in for MuJoCo Warp's collision(): the plugin for installed models, stock otherwise."""
  collider = getattr(m, _ATTR, None)
  if collider is None:
    return _STOCK_COLLISION(m, d, awake_prev)
  return collider.collision(m, d, awake_prev)


def _patch():
  # forward.fwd_position calls collision_driver.collision through the module attribute
  collision_driver.collision = _dispatch
  mjw.collision = _dispatch


def install(mjm: mujoco.MjModel, m, options: Optional[Options] = None) -> Collider:
  """Builds the plugin's data for model ``m`` and routes its collision stage to the plugin.

  Args:
    mjm: the host model ``m`` was made from (hulls and mesh data are read from it).
    m: the MuJoCo Warp model (``mjw.put_model(mjm)``).
    options: tuning parameters; ``Options()`` when omitted.

  Returns:
    The Collider; ``mjw.step``, ``mjw.forward`` and ``mjw.fwd_position`` on ``m`` use it.

  Raises:
    TypeError: arguments of the wrong type.
    ValueError: the models do not match, or the plugin is already installed on ``m``.
  """
  if not isinstance(mjm, mujoco.MjModel):
    raise TypeError(f"install: mjm must be a mujoco.MjModel, got {type(mjm).__name__}")
  if not isinstance(m, mjw.Model):
    raise TypeError(f"install: m must be a mujoco_warp Model (mjw.put_model), got {type(m).__name__}")
  if options is None:
    options = Options()
  elif isinstance(options, dict):
    options = Options.from_dict(options)
  elif not isinstance(options, Options):
    raise TypeError(f"install: options must be mjx_supportfield.Options, got {type(options).__name__}")
  if m.ngeom != mjm.ngeom or m.nmesh != mjm.nmesh:
    raise ValueError(
      f"install: m has {m.ngeom} geoms and {m.nmesh} meshes but mjm has {mjm.ngeom} and {mjm.nmesh};"
      " pass the MjModel that m was made from"
    )
  if getattr(m, _ATTR, None) is not None:
    raise ValueError("install: the plugin is already installed on this model; call uninstall(m) first")
  collider = Collider(mjm, m, options)
  object.__setattr__(m, _ATTR, collider)
  _patch()
  return collider


def uninstall(m) -> None:
  """Returns model ``m`` to MuJoCo Warp's stock collision stage.

  Raises:
    ValueError: the plugin is not installed on ``m``.
  """
  if getattr(m, _ATTR, None) is None:
    raise ValueError("uninstall: the plugin is not installed on this model")
  object.__delattr__(m, _ATTR)


def get_collider(m) -> Optional[Collider]:
  """The Collider installed on ``m``, or None."""
  return getattr(m, _ATTR, None)


def collision(m, d, awake_prev: Optional[wp.array] = None) -> None:
  """Runs only the plugin's collision stage on ``d`` (positions must be current).

  Raises:
    ValueError: the plugin is not installed on ``m``.
  """
  collider = getattr(m, _ATTR, None)
  if collider is None:
    raise ValueError("collision: the plugin is not installed on this model; call install(mjm, m) first")
  collider.collision(m, d, awake_prev)
