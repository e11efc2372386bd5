"""Shared helpers and fixtures of the mjx_supportfield CPU test suite.

Warp compiles every kernel on its first launch (slow on the CPU), so the tests reuse a small
set of models and option combinations; fixtures that own compiled state are module or session
scoped.
"""

import atexit
import contextlib
import ctypes
import os
import shutil
import sys
import tempfile
import types

import numpy as np
import pytest

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
MODELS = os.path.join(ROOT, "models")
if ROOT not in sys.path:
  sys.path.insert(0, ROOT)
# install's disk cache (support fields, SDFs): the test session's own, so that tests neither read
# nor fill the user's; subprocesses inherit it
_USER_CACHE = os.environ.get("MJX_SUPPORTFIELD_CACHE") or os.path.join(
  os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache"), "mjx_supportfield")
_CACHE = tempfile.mkdtemp(prefix="mjx_supportfield_test_cache_")
os.environ["MJX_SUPPORTFIELD_CACHE"] = _CACHE
atexit.register(shutil.rmtree, _CACHE, ignore_errors=True)
# files fetched once into the user's cache (robosuite's, benchmarks/robosuite_arms.py) stay in view
if os.path.isdir(_USER_CACHE):
  for _name in os.listdir(_USER_CACHE):
    if _name.startswith("robosuite-"):
      os.symlink(os.path.join(_USER_CACHE, _name), os.path.join(_CACHE, _name))
# benchmarks/scenelib: the repository's scenes and measures (not part of the installed package)
if os.path.join(ROOT, "benchmarks") not in sys.path:
  sys.path.insert(0, os.path.join(ROOT, "benchmarks"))

import warp as wp  # noqa: E402

wp.config.quiet = True
if hasattr(wp.config, "log_level"):  # Warp >= 1.10 logs module loads at INFO level
  wp.config.log_level = wp.LOG_WARNING

import mujoco  # noqa: E402
import mujoco_warp as mjw  # noqa: E402
from mujoco_warp._src.types import DeterminismType  # noqa: E402

HAS_CUDA = wp.get_cuda_device_count() > 0
# the device the suite runs on: CPU unless asked (CI has no GPU; the GPU lane passes --device cuda)
DEVICE_ENV = "MJX_SF_TEST_DEVICE"


def pytest_addoption(parser):
  parser.addoption(
    "--device",
    default=os.environ.get(DEVICE_ENV, "cpu"),
    help=f"Warp device the tests run on: cpu (default) or cuda / cuda:N (also ${DEVICE_ENV})",
  )


def pytest_configure(config):
  device = config.getoption("--device")
  if device.startswith("cuda") and not HAS_CUDA:
    raise pytest.UsageError(f"--device {device}: Warp finds no CUDA device on this machine")
  wp.set_device(device)


def pytest_collection_modifyitems(config, items):
  """Tests marked ``cpu_only(reason)`` are skipped on a GPU, with the marker's reason."""
  if not config.getoption("--device").startswith("cuda"):
    return
  for item in items:
    mark = item.get_closest_marker("cpu_only")
    if mark is not None:
      reason = mark.kwargs.get("reason") or (mark.args[0] if mark.args else "")
      if not reason:
        raise pytest.UsageError(f"{item.nodeid}: cpu_only needs a reason")
      item.add_marker(pytest.mark.skip(reason=f"CPU only: {reason}"))


def pytest_report_header(config):
  device = wp.get_device()
  name = device.name if device.is_cuda else "cpu"
  return f"mjx_supportfield tests on Warp device {device.alias} ({name})"


def on_gpu() -> bool:
  """Whether the suite runs on a CUDA device (--device cuda)."""
  return wp.get_device().is_cuda


def printed(capfd) -> str:
  """What the process printed since the last read, kernels' printf included: waits for the
  device, whose printf output reaches C's stdout only at a synchronization, and flushes C's
  buffered stdout, which Python's capture does not see until then."""
  wp.synchronize()
  ctypes.CDLL(None).fflush(None)
  return capfd.readouterr().out


@contextlib.contextmanager
def bitwise_repeatable(m):
  """Within the block, runs on the same state give bitwise the same contacts and qpos.

  On the CPU they do as they are. On a GPU contacts are appended with atomics, so their order
  changes from run to run, and MuJoCo Warp's solver sums in atomic order: there bitwise
  repeatability is what ``m.opt.deterministic`` promises, so the block sets it (and restores it).
  """
  saved = m.opt.deterministic
  if on_gpu():
    m.opt.deterministic = DeterminismType.ALL
  try:
    yield
  finally:
    m.opt.deterministic = saved


def sorted_rows(fields: dict) -> dict:
  """Contact fields (name -> array, one row a contact) with the rows in a canonical order: by
  their bytes, so that two sets of contacts compare bitwise whatever order they were written in."""
  n = len(next(iter(fields.values()))) if fields else 0
  rows = [b"".join(np.ascontiguousarray(fields[k][i]).tobytes() for k in sorted(fields)) for i in range(n)]
  order = sorted(range(n), key=rows.__getitem__)
  return {k: v[order] for k, v in fields.items()}


def model_path(name: str) -> str:
  """Path of a scene in models/ ("convex_pile" or "convex_pile.xml")."""
  if not name.endswith(".xml"):
    name += ".xml"
  return os.path.join(MODELS, name)


def load_mjmodel(src: str) -> mujoco.MjModel:
  """MjModel from a scene name in models/ or from an MJCF string."""
  if src.lstrip().startswith("<"):
    return mujoco.MjModel.from_xml_string(src)
  return mujoco.MjModel.from_xml_path(model_path(src))


class Sim(types.SimpleNamespace):
  """mjm, mjd (MuJoCo C, after mj_forward), m (mjw.Model) and d (mjw.Data)."""


def load(src, nworld: int = 1, qpos=None, naconmax=None, mjm=None) -> Sim:
  """Loads a model, runs mj_forward, and makes the MuJoCo Warp Model and Data.

  Args:
    src: scene name in models/, or an MJCF string.
    nworld: number of worlds of the Data.
    qpos: optional (nq,) or (nworld, nq) positions; kinematics is run on the Data.
    naconmax: contact buffer size (MuJoCo Warp's default when None).
    mjm: an already loaded MjModel (src is then ignored).
  """
  mjm = load_mjmodel(src) if mjm is None else mjm
  mjd = mujoco.MjData(mjm)
  mujoco.mj_forward(mjm, mjd)
  m = mjw.put_model(mjm)
  kw = {} if naconmax is None else {"naconmax": naconmax}
  d = mjw.put_data(mjm, mjd, nworld=nworld, **kw)
  sim = Sim(mjm=mjm, mjd=mjd, m=m, d=d)
  if qpos is not None:
    set_qpos(sim, qpos)
  else:
    mjw.kinematics(m, d)
  return sim


def set_qpos(sim: Sim, qpos) -> None:
  """Sets qpos of every world ((nq,) broadcast, or (nworld, nq)) and runs mjw.kinematics."""
  qpos = np.asarray(qpos, dtype=np.float32)
  if qpos.ndim == 1:
    qpos = np.tile(qpos, (sim.d.nworld, 1))
  assert qpos.shape == (sim.d.nworld, sim.mjm.nq)
  sim.d.qpos.assign(qpos)
  mjw.kinematics(sim.m, sim.d)


def contacts(d, world: int) -> types.SimpleNamespace:
  """Host copies of the active contacts of one world: the first d.nacon entries with that worldid.

  Fields: n, dist (n,), pos (n, 3), normal (n, 3) (frame row 0: from geom[0] to geom[1]),
  frame (n, 3, 3), geom (n, 2).
  """
  n = min(int(d.nacon.numpy()[0]), d.naconmax)
  c = d.contact
  sel = c.worldid.numpy()[:n] == world
  frame = c.frame.numpy()[:n][sel].reshape(-1, 3, 3)
  return types.SimpleNamespace(
    n=int(sel.sum()),
    dist=c.dist.numpy()[:n][sel],
    pos=c.pos.numpy()[:n][sel].reshape(-1, 3),
    frame=frame,
    normal=frame[:, 0, :],
    geom=c.geom.numpy()[:n][sel].reshape(-1, 2),
  )


def world_contact_fields(d, world: int) -> dict:
  """The fields that describe one world's contacts (not their places in the constraint rows)."""
  c = contacts(d, world)
  return {"dist": c.dist, "pos": c.pos, "frame": c.frame, "geom": c.geom}


def contact_table(d, world: int) -> dict:
  """{(g1, g2) unordered: (dist, normal oriented from min geom to max geom, pos)} of the deepest
  contact of each geom pair in one world of a MuJoCo Warp Data."""
  c = contacts(d, world)
  out = {}
  for i in range(c.n):
    g1, g2 = (int(x) for x in c.geom[i])
    n = c.normal[i].astype(np.float64)
    if g1 > g2:
      g1, g2, n = g2, g1, -n
    if (g1, g2) not in out or c.dist[i] < out[(g1, g2)][0]:
      out[(g1, g2)] = (float(c.dist[i]), n, c.pos[i].astype(np.float64))
  return out


def mjc_contact_table(mjm, mjd) -> dict:
  """Same as contact_table for MuJoCo C's contacts in mjd (call mj_forward/mj_collision first)."""
  out = {}
  for i in range(mjd.ncon):
    con = mjd.contact[i]
    g1, g2 = int(con.geom1), int(con.geom2)
    n = np.array(con.frame[:3], dtype=np.float64)
    if g1 > g2:
      g1, g2, n = g2, g1, -n
    if (g1, g2) not in out or con.dist < out[(g1, g2)][0]:
      out[(g1, g2)] = (float(con.dist), n, np.array(con.pos, dtype=np.float64))
  return out


def free_body_qpos(mjm, qpos, body: str, pos=None, quat=None):
  """Writes position / quaternion of a body's free joint into a qpos vector (in place)."""
  b = mjm.body(body)
  jnt = int(mjm.body_jntadr[b.id])
  assert jnt >= 0 and mjm.jnt_type[jnt] == mujoco.mjtJoint.mjJNT_FREE, body
  adr = int(mjm.jnt_qposadr[jnt])
  if pos is not None:
    qpos[adr : adr + 3] = pos
  if quat is not None:
    q = np.asarray(quat, dtype=np.float64)
    qpos[adr + 3 : adr + 7] = q / np.linalg.norm(q)
  return qpos


def random_quat(rng, max_angle=np.pi):
  """Random unit quaternion (w, x, y, z) with rotation angle <= max_angle."""
  axis = rng.normal(size=3)
  axis /= np.linalg.norm(axis)
  ang = rng.uniform(-max_angle, max_angle)
  return np.concatenate([[np.cos(ang / 2)], np.sin(ang / 2) * axis])


def angle_deg(a, b) -> float:
  """Angle between two vectors in degrees."""
  a = np.asarray(a, dtype=np.float64)
  b = np.asarray(b, dtype=np.float64)
  c = np.dot(a, b) / (np.linalg.norm(a) * np.linalg.norm(b))
  return float(np.degrees(np.arccos(np.clip(c, -1.0, 1.0))))


def geom_id(mjm, name: str) -> int:
  return int(mujoco.mj_name2id(mjm, mujoco.mjtObj.mjOBJ_GEOM, name))


def quat_mat(q) -> np.ndarray:
  """Rotation matrix of a unit quaternion (w, x, y, z)."""
  m = np.zeros(9)
  mujoco.mju_quat2Mat(m, np.asarray(q, dtype=np.float64))
  return m.reshape(3, 3)


def unit(v) -> np.ndarray:
  """v / |v|."""
  v = np.asarray(v, dtype=np.float64)
  return v / np.linalg.norm(v)
