"""Meshes resting on a plane stay put for 500 mjw.step calls under the plugin (no sinking)."""

import mujoco
import mujoco_warp as mjw
import numpy as np
import pytest

import mjx_supportfield as sf
from conftest import load

NSTEP = 500


@pytest.fixture(scope="module")
def trajectory():
  sim = load("mesh_on_plane", nworld=1)
  mjm = sim.mjm
  sf.install(mjm, sim.m)
  qpos = [sim.d.qpos.numpy()[0].copy()]
  for _ in range(NSTEP):
    mjw.step(sim.m, sim.d)
    qpos.append(sim.d.qpos.numpy()[0].copy())
  stats = sf.get_collider(sim.m).stats(sim.d)
  sf.uninstall(sim.m)
  return mjm, np.array(qpos, dtype=np.float64), stats


def body_qpos(mjm, qpos, body):
  adr = mjm.jnt_qposadr[mjm.body_jntadr[mjm.body(body).id]]
  return qpos[:, adr : adr + 3], qpos[:, adr + 3 : adr + 7]


def test_plugin_ran(trajectory):
  _, _, stats = trajectory
  assert stats["pairs"] > 0


def test_no_nan(trajectory):
  _, qpos, _ = trajectory
  assert np.all(np.isfinite(qpos))


@pytest.mark.parametrize("body", ["boxmesh", "mesh1", "cylmesh"])
def test_height_stays(trajectory, body):
  mjm, qpos, _ = trajectory
  pos, _ = body_qpos(mjm, qpos, body)
  z = pos[:, 2]
  dev = np.abs(z - z[0])
  assert dev.max() <= 2e-3, f"{body}: height moved by {dev.max() * 1e3:.3f} mm (step {dev.argmax()})"
  # no sinking: no net downward drift over the second half and no steady descent
  half = len(z) // 2
  drift = z[-1] - z[half]
  assert drift > -2e-5, f"{body}: sank {-drift * 1e3:.4f} mm over the last {len(z) - half} steps"
  down = np.diff(z[half:]) < -1e-9
  assert down.mean() < 0.9, f"{body}: height decreased in {down.mean():.0%} of the last steps"


def test_boxmesh_stays_flat_and_in_place(trajectory):
  mjm, qpos, _ = trajectory
  pos, quat = body_qpos(mjm, qpos, "boxmesh")
  assert np.max(np.linalg.norm(pos[:, :2] - pos[0, :2], axis=1)) < 2e-3
  # tilt of the body z axis
  zaxis = np.empty((len(quat), 3))
  for i, q in enumerate(quat):
    m = np.empty(9)
    mujoco.mju_quat2Mat(m, q / np.linalg.norm(q))
    zaxis[i] = m.reshape(3, 3)[:, 2]
  tilt = np.degrees(np.arccos(np.clip(zaxis[:, 2], -1, 1)))
  assert tilt.max() < 1.0, f"boxmesh tilted by {tilt.max():.3f} deg"
