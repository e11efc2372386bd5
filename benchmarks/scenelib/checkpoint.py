"""Checkpoints of a long run of many worlds: the per-world state written to disk and read back
into a fresh Data, so that benchmarks/soak.py can run in segments.

A checkpoint (``.npz``) holds each world's time, qpos, qvel, act and, unless it would grow too
large, qacc_warmstart (the solver's warm start), with the caller's metadata as JSON. Resuming
writes the state into a fresh Data from ``mjw.put_data`` and lets ``mjw.forward`` recompute
everything derived from it.
"""

import hashlib
import json
import os

import mujoco
import mujoco_warp as mjw
import numpy as np


class CheckpointError(ValueError):
  """A checkpoint that is missing, of another format, or not the run asked for."""


STATE = ("time", "qpos", "qvel", "act")  # per-world state a checkpoint always holds
WARMSTART = "qacc_warmstart"  # held too, unless the checkpoint would grow past --save-max-mib
FORMAT = 1  # checkpoint format version
MIB = 1 << 20


def scene_sha256(path: str) -> str:
  """sha256 of the scene's XML text (the pile scenes hold their meshes inline)."""
  with open(path, "rb") as f:
    return hashlib.sha256(f.read()).hexdigest()


def read_state(d, fields=STATE + (WARMSTART,)) -> dict:
  """Host copies of the per-world state arrays ``fields`` of ``d``."""
  return {f: getattr(d, f).numpy().copy() for f in fields}


def write_state(d, state: dict):
  """Writes the per-world arrays of ``state`` (as read_state gives them) into ``d``."""
  for f, a in state.items():
    dst = getattr(d, f)
    if tuple(dst.shape) != a.shape:
      raise ValueError(f"checkpoint's {f} has shape {a.shape}, the Data's {tuple(dst.shape)}")
    if a.size:
      dst.assign(a)


def load_checkpoint(path: str) -> tuple:
  """(meta, per-world state arrays) of a checkpoint written by save_checkpoint."""
  if not os.path.exists(path):
    raise CheckpointError(f"no checkpoint at {path}")
  with np.load(path, allow_pickle=False) as z:
    meta = json.loads(str(z["meta"]))
    state = {k[len("state_"):]: z[k] for k in z.files if k.startswith("state_")}
  if meta.get("format") != FORMAT:
    raise CheckpointError(f"{path}: checkpoint format {meta.get('format')}, this script reads {FORMAT}")
  return meta, state


def check_resume(meta: dict, path: str, scene: str, sha: str, nworld, nconmax):
  """Raises CheckpointError when the run asked for (the soak's ``--nworld`` and ``--nconmax``;
  None: the checkpoint's) is not the checkpoint's."""
  bad = []
  if sha != meta["scene_sha256"]:
    bad.append(f"scene {scene} (sha256 {sha[:12]}) is not the checkpoint's {meta['scene']}"
               f" (sha256 {meta['scene_sha256'][:12]})")
  if nworld is not None and nworld != meta["nworld"]:
    bad.append(f"--nworld {nworld} but the checkpoint has {meta['nworld']} worlds")
  if nconmax is not None and nconmax != meta["ref"]["nconmax"]:
    bad.append(f"--nconmax {nconmax} but the checkpoint used {meta['ref']['nconmax']}")
  if bad:
    raise CheckpointError(f"cannot resume from {path}: " + "; ".join(bad))


def resume_start(mjm, m, meta: dict, state: dict):
  """Fresh Data holding the checkpoint's state, its derived quantities recomputed."""
  nconmax = meta["ref"]["nconmax"]
  mjd = mujoco.MjData(mjm)
  mujoco.mj_forward(mjm, mjd)
  d = mjw.put_data(mjm, mjd, nworld=meta["nworld"], nconmax=nconmax, njmax=6 * nconmax)
  write_state(d, state)
  mjw.forward(m, d)  # leaves qacc_warmstart alone: the next step starts from the saved one
  return d


def save_checkpoint(path: str, d, meta: dict, max_mib: float) -> dict:
  """Writes ``meta`` and the state of ``d`` to ``path`` (through a temporary file, so an existing
  checkpoint is replaced whole or not at all); returns what was written."""
  state = read_state(d, STATE)
  warm = read_state(d, (WARMSTART,))
  if sum(a.nbytes for a in state.values()) + warm[WARMSTART].nbytes <= max_mib * MIB:
    state.update(warm)
  return save_state(path, state, meta)


def save_state(path: str, state: dict, meta: dict) -> dict:
  """Writes ``meta`` and the per-world arrays ``state`` (as read_state gives them) to ``path``,
  atomically; returns what was written."""
  meta = dict(meta, warmstart_saved=WARMSTART in state)
  tmp = path + ".tmp"
  with open(tmp, "wb") as f:
    np.savez_compressed(f, meta=np.array(json.dumps(meta)), **{f"state_{k}": v for k, v in state.items()})
  os.replace(tmp, path)
  return {"path": path, "mib": os.path.getsize(path) / MIB, "warmstart_saved": WARMSTART in state}
