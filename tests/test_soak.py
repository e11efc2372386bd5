"""benchmarks/soak.py's checkpoints: a resumed soak continues the state exactly, a mismatched one is refused."""

import os
import sys

import mujoco
import mujoco_warp as mjw
import numpy as np
import pytest
from conftest import ROOT

sys.path.insert(0, os.path.join(ROOT, "benchmarks"))

import soak  # noqa: E402

from mjx_supportfield import Options  # noqa: E402
from mjx_supportfield.install import install  # noqa: E402

SCENE = os.path.join(ROOT, "benchmarks", "scenes", "pile_32_128.xml")
NSTEP = 10


def _meta(d, ref):
  return {"format": soak.FORMAT, "scene": os.path.basename(SCENE), "scene_path": SCENE,
          "scene_sha256": soak.scene_sha256(SCENE), "nworld": d.nworld, "ref": ref, "history": soak.new_history(),
          "versions": {}}


@pytest.mark.slow
def test_resume_continues_bitwise(tmp_path):
  """Without the plugin's warm start (the one cache a resume loses), N steps, a checkpoint, and N
  more steps from a fresh Data give the qpos of 2N steps in one go, bit for bit."""
  mjm = mujoco.MjModel.from_xml_path(SCENE)
  mjm.opt.enableflags |= mujoco.mjtEnableBit.mjENBL_ENERGY
  m = mjw.put_model(mjm)
  install(mjm, m, Options(warm_start=False))
  d, ref = soak.fresh_start(mjm, m, 2, None)
  for _ in range(NSTEP):
    mjw.step(m, d)
  path = str(tmp_path / "ck.npz")
  saved = soak.save_checkpoint(path, d, _meta(d, ref), 15.0)
  assert saved["warmstart_saved"]
  for _ in range(NSTEP):
    mjw.step(m, d)
  meta, state = soak.load_checkpoint(path)
  assert meta["ref"] == ref and set(state) == set(soak.STATE) | {soak.WARMSTART}
  d2 = soak.resume_start(mjm, m, meta, state)
  for _ in range(NSTEP):
    mjw.step(m, d2)
  np.testing.assert_array_equal(d2.qpos.numpy(), d.qpos.numpy())
  np.testing.assert_array_equal(d2.time.numpy(), d.time.numpy())


@pytest.mark.parametrize("nworld, nconmax, needle", [(8, None, "--nworld 8"), (None, 5, "--nconmax 5")])
def test_mismatch_refused(capsys, nworld, nconmax, needle):
  meta = {"scene": "pile_32_128.xml", "scene_sha256": soak.scene_sha256(SCENE), "nworld": 2,
          "ref": {"nconmax": 100}, "versions": {}}
  with pytest.raises(SystemExit) as e:
    soak.check_resume(meta, "ck.npz", SCENE, meta["scene_sha256"], nworld, nconmax)
  assert e.value.code == 2 and needle in capsys.readouterr().err


def test_other_scene_refused(capsys):
  meta = {"scene": "pile_32_128.xml", "scene_sha256": soak.scene_sha256(SCENE), "nworld": 2,
          "ref": {"nconmax": 100}, "versions": {}}
  other = os.path.join(ROOT, "benchmarks", "scenes", "primitives_32.xml")
  with pytest.raises(SystemExit) as e:
    soak.check_resume(meta, "ck.npz", other, soak.scene_sha256(other), 2, None)
  assert e.value.code == 2 and "sha256" in capsys.readouterr().err
