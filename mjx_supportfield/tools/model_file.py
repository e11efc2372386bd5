"""The model files the command line and the benchmarks read: MJCF, or a compiled model (``.mjb``,
``mujoco.mj_saveModel``'s) for scenes built by code, such as mjlab's tasks."""

import mujoco


def load_model(path: str) -> mujoco.MjModel:
  """The MuJoCo model in ``path``: a compiled model for a ``.mjb`` file, else MJCF."""
  if path.endswith(".mjb"):
    return mujoco.MjModel.from_binary_path(path)
  return mujoco.MjModel.from_xml_path(path)
