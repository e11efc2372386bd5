"""Installing the plugin on a MuJoCo Warp model, and the dispatcher that routes stepping to it."""

from typing import Optional

import mujoco
import mujoco_warp as mjw
import numpy as np
import warp as wp
from mujoco_warp._src import collision_driver
from mujoco_warp._src import io as mjw_io

from mjx_supportfield.collider import STOCK_COLLISION as _STOCK_COLLISION
from mjx_supportfield.collider import Collider
from mjx_supportfield.launch import first_use
from mjx_supportfield.options import Options
from mjx_supportfield.types import CONVEX_TYPES

_ATTR = "_mjx_supportfield_collider"  # where a model keeps its Collider
_STOCK_RESET = mjw_io.reset_data


def _dispatch(m, d, awake_prev: Optional[wp.array] = None):
  """Stand-in for MuJoCo Warp's collision(): the plugin for installed models, stock otherwise."""
  collider = getattr(m, _ATTR, None)
  if collider is None:
    return _STOCK_COLLISION(m, d, awake_prev)
  return _collide(collider, m, d, awake_prev)


def _collide(collider: Collider, m, d, awake_prev: Optional[wp.array]):
  if first_use.active:  # until each installed model's first step is done: notes on compiling kernels
    return first_use.collide(collider, m, d, awake_prev)
  return collider.collision(m, d, awake_prev)


def _geom_name(mjm: mujoco.MjModel, g: int) -> str:
  return mujoco.mj_id2name(mjm, mujoco.mjtObj.mjOBJ_GEOM, g) or f"geom {g}"


def _check_values(mjm: mujoco.MjModel, m) -> None:
  """Values the plugin's kernels read must be finite, and primitive sizes non-negative (the
  compiler checks this, but a model can be edited after compiling, per world too)."""
  if mjm.ngeom == 0:
    return
  convex = np.isin(np.asarray(mjm.geom_type), [int(t) for t in CONVEX_TYPES])
  for field, geoms in (("geom_margin", None), ("geom_gap", None), ("geom_size", convex), ("geom_aabb", convex),
                       ("geom_rbound", convex)):
    values = getattr(m, field).numpy()
    values = values.reshape(values.shape[0], mjm.ngeom, -1)  # (worlds batched, ngeom, values)
    bad = ~np.isfinite(values).all(axis=(0, 2))
    if field == "geom_size":
      bad |= (values < 0).any(axis=(0, 2))
    if geoms is not None:
      bad &= geoms
    if bad.any():
      g = int(np.nonzero(bad)[0][0])
      raise ValueError(f"install: geom '{_geom_name(mjm, g)}': {field} is {values[:, g].tolist()}; expected finite"
                       " values (sizes >= 0)")
  vert = m.mesh_vert.numpy()
  if m.nmesh and not np.isfinite(vert).all():
    meshid = int(np.searchsorted(np.asarray(mjm.mesh_vertadr), np.nonzero(~np.isfinite(vert).all(axis=1))[0][0],
                                 side="right") - 1)
    name = mujoco.mj_id2name(mjm, mujoco.mjtObj.mjOBJ_MESH, meshid) or f"mesh {meshid}"
    raise ValueError(f"install: mesh '{name}': mesh_vert holds non-finite values")


def _reset_data(m, d, reset: Optional[wp.array] = None):
  """Stand-in for MuJoCo Warp's reset_data(): also drops the plugin's history of the reset worlds
  (warm-start normals, sweep-and-prune order), so a reset world repeats its run bit for bit."""
  _STOCK_RESET(m, d, reset)
  Collider.reset_worlds(d, reset)


def _patch():
  # forward.fwd_position calls collision_driver.collision through the module attribute
  collision_driver.collision = _dispatch
  mjw.collision = _dispatch
  # reset_data_keyframe calls io.reset_data through the module attribute too
  mjw_io.reset_data = _reset_data
  mjw.reset_data = _reset_data


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
    ValueError: the models do not match, the plugin is already installed on ``m``, or a geom's
      size, margin, gap or bounds (or a mesh vertex) is not finite, or a primitive's size negative.
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
  _check_values(mjm, m)
  with first_use.stage("install (support fields and SDFs)"):
    collider = Collider(mjm, m, options)
  first_use.arm(collider)
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
  first_use.disarm(getattr(m, _ATTR))
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
  _collide(collider, m, d, awake_prev)
