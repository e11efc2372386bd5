"""Soak run: many steps of a pile through the plugin, checking the state as it goes.

  python benchmarks/soak.py [--scene benchmarks/scenes/pile_256_128.xml] [--nworld 1024]
                            [--steps 100000] [--chunk 500] [--minutes M] [--json OUT]
                            [--save CK.npz [--save-every N]] [--resume CK.npz] [--save-failing F.npz]

The worlds start from the scene's initial state (its keyframe, if it has one; a pile's bodies
dropped from rest), each with a small random velocity so they differ. Steps run ``chunk`` at a
time from one captured graph (a CUDA graph on a GPU; a last, shorter chunk runs uncaptured).
After every chunk the run checks, over all worlds:
  - qpos and qvel finite (a NaN anywhere is a failure);
  - total energy (MuJoCo's kinetic + potential) bounded: at most the highest energy of MuJoCo C's
    own 500-step run from rest plus the random velocities' kinetic energy (never below the largest
    initial energy), plus 1 % of the energy span of C's run. A dropped pile only loses energy, so
    its bound is its initial energy; an actuated robot's actuators add some, as they do in C;
  - no overflow bit in d.overflow, no dropped broad-phase pairs;
  - nothing through the ground: no moving collision geom's centre inside a static box, under a
    static plane or in a heightfield's slab (under its surface, above its base; below the slab
    only for a robot whose trunk is under the surface: Ground.geoms_through) at two chunk ends
    in a row (in one episode). A
    geom's centre inside the ground has sunk by more than its own radius (half its smallest side
    for a box), which no resting contact allows; a Go1 under random controls jams a calf that
    deep into a stair or a slope now and then in MuJoCo C too, and it comes out again
    (soak_rate.py: at 2.4e-4 of MuJoCo C's world-checks), so such a geom at one chunk end is
    counted and reported, and one still there at the next fails the chunk. Centres, not bodies'
    centres of mass: a thin limb's centre of mass can lie outside its capsules, below the
    surface while they rest on it.

Terrain robots (``--ctrl-noise``, ``--reset-every``), as an RL run drives them: every chunk each
world's controls are the keyframe's plus uniform noise of that amplitude, and after every chunk
the worlds whose episode ends (world w after chunks k with (k + w) % N == N - 1: a staggered
fraction 1/N of the worlds each time) are reset as mjlab resets them: ``mjw.reset_data`` with that
mask, then the keyframe's state shifted horizontally by up to 5 cm and each robot lifted clear
of the ground it would sink into there (as a spawn on terrain must be; SPAWN_POOL such spawns are
made at the first reset and drawn at random), small random velocities and ``mjw.forward``. A
world in which a robot has walked off the terrain (its root beyond every static heightfield and
box, seen from above) ends its episode too, as an RL run's out-of-bounds termination ends it; its
geoms are not judged in that chunk, and the count is reported. Random controls feed the robots
energy, so the energy bound is reported but not judged while they are on.
The run stops at ``steps`` (in all, counted over every segment) or before a chunk that would end
more than ``minutes`` after the script started (setup and compiling included; judged by the
slowest chunk so far, the first chunk always runs), and the JSON says which.

A failure to replay: ``--save-failing F.npz`` keeps the state of the last two chunk starts (with
the controls the driving set) and writes the older one when a chunk first fails, the checkpoint's
format plus ``ctrl``, ``start_step`` and ``failed_at``: a geom stuck in the ground fails at the
second of two chunk ends, and the chunk before shows it going in.

Segments. A run too long for one sitting runs as several segments: ``--save CK.npz`` writes a
checkpoint when the segment stops (and every ``--save-every`` chunks, written atomically), and
``--resume CK.npz`` continues it in a fresh process, counting steps from the saved count up to
``--steps`` in all. The checkpoint holds each world's time, qpos, qvel, act and qacc_warmstart (the
solver's warm start), the energy bound's references (initial energies, potential span, bound),
nconmax, the scene's path and sha256, nworld, the steps done, and the history (segments, chunks,
wall seconds, worst energy, overflow bits, dropped pairs, failures, the trace). A resume refuses a
scene whose sha256 differs or an ``--nworld`` / ``--nconmax`` that differs from the checkpoint's.
The state is written into a fresh Data from ``mjw.put_data``, then ``mjw.forward`` recomputes
everything derived from it. Not carried over: the plugin's caches (MPR warm-start normals,
sweep-and-prune order) start cold, so a resumed run is not bitwise the run that never stopped
(with ``Options(warm_start=False)`` it is, on the CPU); ctrl, applied forces and mocap stay at the
model's defaults as in the first segment (the soak never sets them); the sleep state is not saved
(the piles do not enable sleeping). qacc_warmstart is left out (the solver's first step after the
resume starts cold, which moves the trajectory a little) when it would make the checkpoint's
arrays larger than ``--save-max-mib``: 1024 worlds of the 256-mesh pile take 13 MiB for qpos and
qvel and 6 more for qacc_warmstart, and zlib hardly shrinks them.
"""

import argparse
import json
import os
import sys
import time

import mujoco
import mujoco_warp as mjw
import numpy as np
import warp as wp

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.dirname(HERE))
sys.path.insert(0, HERE)

import make_scenes  # noqa: E402

from scenelib import real_scenes  # noqa: E402

from mjx_supportfield.tools import bench  # noqa: E402
from scenelib.checkpoint import FORMAT  # noqa: E402
from scenelib.checkpoint import STATE  # noqa: E402
from scenelib.checkpoint import WARMSTART  # noqa: E402
from scenelib.checkpoint import CheckpointError  # noqa: E402
from scenelib.checkpoint import check_resume  # noqa: E402
from scenelib.checkpoint import load_checkpoint  # noqa: E402
from scenelib.checkpoint import read_state  # noqa: E402
from scenelib.checkpoint import resume_start  # noqa: E402
from scenelib.checkpoint import save_checkpoint  # noqa: E402
from scenelib.checkpoint import save_state  # noqa: E402
from scenelib.checkpoint import scene_sha256  # noqa: E402
from scenelib.checkpoint import write_state  # noqa: E402
from mjx_supportfield.driver import get_collider  # noqa: E402
from mjx_supportfield.driver import install  # noqa: E402

SPEED = 0.05  # m/s (and rad/s) of the random initial velocities
RESET_SHIFT = 0.05  # m: how far a reset world's robots are moved horizontally from the keyframe
LIFT_CLEARANCE = 0.002  # m: a reset robot's lowest geom above the ground it was lifted out of
# reset spawns (each a shift and its lift) prepared once and drawn at random: lifting every reset
# world's robots with MuJoCo C on the host took most of a chunk's time at thousands of worlds
SPAWN_POOL = 256


def energy(d) -> np.ndarray:
  """Per-world total energy (kinetic + potential)."""
  return d.energy.numpy().sum(axis=1)


def fail(message: str):
  """Exits with ``message`` on stderr and status 2 (failed checks exit with 1)."""
  print(f"soak: {message}", file=sys.stderr)
  sys.exit(2)


def new_history() -> dict:
  """The summaries a soak carries from segment to segment."""
  return {"steps": 0, "segments": 0, "seconds": 0.0, "chunks": 0, "energy_max_seen": None,
          "nonfinite_chunks": 0, "overflow_bits": 0, "dropped_pairs_max": 0, "failures": [], "trace": []}


def reference_rollout(mjm, nstep: int = 500) -> tuple:
  """MuJoCo C's run of the scene from its initial state at rest: the state it ends in, and the
  highest and lowest total energy on the way. A pile only loses energy; an actuated robot's
  actuators can add some, so the bound follows what MuJoCo C itself reaches."""
  mjd = real_scenes.initial_data(mjm)
  start = float(mjd.energy.sum())
  high = low = start
  for _ in range(nstep):
    mujoco.mj_step(mjm, mjd)
    high, low = max(high, float(mjd.energy.sum())), min(low, float(mjd.energy.sum()))
  return mjd, start, high, low


def fresh_start(mjm, m, nworld: int, nconmax_arg):
  """Data for a new soak: scene's initial state, random velocities; and the energy references."""
  settled, e_start, e_high, e_low = reference_rollout(mjm)
  mjd = real_scenes.initial_data(mjm)
  # room for the contacts at rest and for those of the first step (a robot scene may start in contact)
  nconmax = nconmax_arg or 2 * max(settled.ncon, mjd.ncon) + 16
  d = mjw.put_data(mjm, mjd, nworld=nworld, nconmax=nconmax, njmax=6 * nconmax)
  rng = np.random.default_rng(0)
  d.qvel.assign((SPEED * rng.uniform(-1, 1, size=(nworld, mjm.nv))).astype(np.float32))
  mjw.forward(m, d)
  e0 = energy(d)
  span = e_high - e_low  # energy the scene moves through in MuJoCo C
  kick = max(float(e0.max()) - e_start, 0.0)  # the random velocities' kinetic energy
  ref = {"nconmax": int(nconmax), "energy_initial": e0.tolist(), "energy_initial_max": float(e0.max()),
         "energy_reference_max": e_high, "potential_span": span,
         "energy_bound": max(float(e0.max()), e_high + kick) + 0.01 * abs(span)}
  return d, ref


def check_chunk(d, collider, nworld: int, limit, ground: "Ground", before=frozenset()) -> tuple:
  """(trace row, list of failed checks, the (world, geom) pairs in the ground) for the state of
  ``d`` after a chunk (``limit``: the energy bound, or None where it is not judged; ``before``:
  the pairs in the ground at the chunk end before, of worlds not reset since)."""
  qpos, qvel = d.qpos.numpy(), d.qvel.numpy()
  finite = bool(np.isfinite(qpos).all() and np.isfinite(qvel).all())
  e = energy(d)
  overflow = int(np.bitwise_or.reduce(d.overflow.numpy().ravel()))
  stats = collider.stats(d)
  off = ground.off_terrain(d)
  through = ground.geoms_through(d, skip=off)
  stuck = sorted(set(through) & set(before))
  row = {"finite": finite, "energy_max": float(np.nanmax(e)), "energy_mean": float(np.nanmean(e)),
         "overflow_bits": overflow, "dropped_pairs": int(sum(stats["dropped_pairs_per_world"])),
         "contacts_per_world": min(int(d.nacon.numpy()[0]), d.naconmax) / nworld,
         "geoms_through_ground": len(through), "geoms_stuck": len(stuck), "worlds_off_terrain": int(off.sum())}
  bad = []
  if not finite:
    bad.append("non-finite state")
  if limit is not None and row["energy_max"] > limit:
    bad.append(f"energy {row['energy_max']:.4g} > bound {limit:.4g}")
  if overflow or row["dropped_pairs"]:
    bad.append(f"overflow bits {overflow}, dropped pairs {row['dropped_pairs']}")
  if stuck:
    bad.append(f"{len(stuck)} geoms in the ground at two chunk ends in a row, first (world, geom) {stuck[:3]}")
  return row, bad, through


class Ground:
  """The static geoms (boxes, planes, heightfields) and the collision geoms that move over them:
  a moving geom's centre inside one of them has gone through the ground."""

  def __init__(self, mjm):
    self.mjm = mjm
    self.static = real_scenes.static_geoms(mjm)
    self.moving = [g for g in range(mjm.ngeom) if mjm.body_weldid[mjm.geom_bodyid[g]] != 0
                   and (mjm.geom_contype[g] or mjm.geom_conaffinity[g])]
    self.roots = real_scenes.free_bodies(mjm)
    # each moving geom's free root body (its column in self.roots), -1 for a geom without one
    root_of = {b: i for i, b in enumerate(self.roots)}
    self.root_column = np.array([root_of.get(int(mjm.body_rootid[mjm.geom_bodyid[g]]), -1) for g in self.moving])
    mjd = mujoco.MjData(mjm)
    mujoco.mj_kinematics(mjm, mjd)  # static geoms sit where they are in every world
    self.geom_xpos, self.geom_xmat = mjd.geom_xpos.copy(), mjd.geom_xmat.copy()
    self.over = real_scenes.static_extent(mjm, self.static, self.geom_xpos, self.geom_xmat)

  def off_terrain(self, d) -> np.ndarray:
    """Per world: whether a free body's root has left the ground, seen from above."""
    if not self.static or not self.roots:
      return np.zeros(d.nworld, dtype=bool)
    return ~self.over(d.xpos.numpy()[:, self.roots, :2]).all(axis=1)

  def geoms_through(self, d, skip=None) -> list:
    """(world, geom name) of every moving collision geom whose centre is inside the ground, in
    the worlds ``skip`` (a mask) does not exclude. Under a heightfield that is its slab, down to
    the base: a foot hanging over the terrain's edge sinks below the slab, and can swing under it,
    with no contact in MuJoCo C either. Where a free body's own centre is under the surface (a
    robot that went through), each of its geoms under the surface counts, below the slab too."""
    if not self.static or not self.moving:
      return []
    centres = d.geom_xpos.numpy()[:, self.moving]
    inside = real_scenes.inside_static(self.mjm, centres, self.geom_xpos, self.geom_xmat, self.static,
                                       below_slab=False)
    if self.roots:
      sunk = real_scenes.inside_static(self.mjm, d.xpos.numpy()[:, self.roots], self.geom_xpos, self.geom_xmat,
                                       self.static)
      if sunk.any():  # only then can a geom below a slab count: test the geoms again there alone
        sunk = np.concatenate([sunk, np.zeros((len(sunk), 1), dtype=bool)], axis=1)  # column -1: no free root
        worlds = np.flatnonzero(sunk.any(axis=1))
        under = real_scenes.inside_static(self.mjm, centres[worlds], self.geom_xpos, self.geom_xmat, self.static)
        inside[worlds] |= under & sunk[worlds][:, self.root_column]
    if skip is not None:
      inside &= ~np.asarray(skip)[:, None]
    return [(int(w), self.mjm.geom(self.moving[i]).name) for w, i in zip(*np.nonzero(inside))]


class Episodes:
  """RL-style driving of the worlds (--ctrl-noise, --reset-every): random controls about the
  keyframe's each chunk, and staggered masked resets to the keyframe."""

  def __init__(self, mjm, m, nworld: int, noise: float, every: int):
    self.mjm, self.m, self.nworld, self.noise, self.every = mjm, m, nworld, noise, every
    self.rng = np.random.default_rng(1)
    start = real_scenes.initial_data(mjm)
    self.qpos0, self.ctrl0 = start.qpos.copy(), start.ctrl.copy()
    self.scratch = mujoco.MjData(mjm)  # where a reset pose is checked against the ground
    self.static = set(real_scenes.static_geoms(mjm))
    self.resets = 0
    self.spawns = None  # SPAWN_POOL lifted poses, made at the first reset

  def drive(self, d):
    """New controls for the next chunk."""
    if self.noise and self.mjm.nu:
      ctrl = self.ctrl0 + self.noise * self.rng.uniform(-1, 1, size=(self.nworld, self.mjm.nu))
      d.ctrl.assign(ctrl.astype(np.float32))

  def reset(self, d, chunk: int, ended=None) -> np.ndarray:
    """Resets the worlds whose episode ends after ``chunk``, and those ``ended`` marks (a robot
    off the terrain); returns which worlds it reset."""
    mask = np.zeros(self.nworld, dtype=bool) if ended is None else np.asarray(ended, dtype=bool).copy()
    if self.every:
      mask |= (chunk + np.arange(self.nworld)) % self.every == self.every - 1
    if not mask.any():
      return mask
    mjw.reset_data(self.m, d, reset=wp.array(mask, dtype=bool))
    qpos, qvel, ctrl = d.qpos.numpy(), d.qvel.numpy(), d.ctrl.numpy()
    if self.spawns is None:
      self.spawns = [self.lifted(self.shifted()) for _ in range(min(SPAWN_POOL, self.nworld))]
    for w in np.nonzero(mask)[0]:
      qpos[w], ctrl[w] = self.spawns[self.rng.integers(len(self.spawns))], self.ctrl0
      qvel[w] = SPEED * self.rng.uniform(-1, 1, size=self.mjm.nv)
    d.qpos.assign(qpos)
    d.qvel.assign(qvel)
    d.ctrl.assign(ctrl)
    mjw.forward(self.m, d)
    self.resets += int(mask.sum())
    return mask

  def shifted(self) -> np.ndarray:
    """The keyframe's qpos with each free body moved horizontally by up to RESET_SHIFT."""
    q = self.qpos0.copy()
    for b in real_scenes.free_bodies(self.mjm):
      adr = self.mjm.jnt_qposadr[self.mjm.body_jntadr[b]]
      q[adr:adr + 2] += self.rng.uniform(-RESET_SHIFT, RESET_SHIFT, size=2)
    return q

  def lifted(self, qpos: np.ndarray) -> np.ndarray:
    """``qpos`` with each free body raised until its tree's geoms clear the static ground by
    LIFT_CLEARANCE (a keyframe shifted over rough terrain can put a foot into a bump)."""
    mjm, q, static = self.mjm, qpos.copy(), self.static
    for _ in range(4):  # a lift can bring a geom onto a higher neighbour's bump: check again
      self.scratch.qpos[:] = q
      mujoco.mj_kinematics(mjm, self.scratch)
      mujoco.mj_collision(mjm, self.scratch)
      sink = {}
      for c in self.scratch.contact[:self.scratch.ncon]:
        g1, g2 = int(c.geom[0]), int(c.geom[1])
        if (g1 in static) != (g2 in static) and c.dist < 0:
          root = int(mjm.body_rootid[mjm.geom_bodyid[g2 if g1 in static else g1]])
          sink[root] = max(sink.get(root, 0.0), -float(c.dist))
      if not sink:
        break
      for root, depth in sink.items():
        q[mjm.jnt_qposadr[mjm.body_jntadr[root]] + 2] += depth + LIFT_CLEARANCE
    return q


def record(hist: dict, row: dict, bad: list):
  """Adds a chunk's row and failed checks to the history."""
  hist["trace"].append(row)
  hist["chunks"] += 1
  seen = hist["energy_max_seen"]
  hist["energy_max_seen"] = row["energy_max"] if seen is None else max(seen, row["energy_max"])
  hist["nonfinite_chunks"] += not row["finite"]
  hist["overflow_bits"] |= row["overflow_bits"]
  hist["dropped_pairs_max"] = max(hist["dropped_pairs_max"], row["dropped_pairs"])
  if bad:
    hist["failures"].append({"step": row["step"], "segment": row["segment"], "what": bad})


def summary(hist: dict, ref: dict) -> dict:
  """The history's summaries for the report (no trace, no failure list)."""
  out = {k: v for k, v in hist.items() if k not in ("trace", "failures")}
  out["failing_chunks"] = len(hist["failures"])
  seen, bound = hist["energy_max_seen"], ref["energy_bound"]
  out["energy_bound_ratio_worst"] = seen / bound if seen is not None and bound else None
  return out


def capture(m, d, nstep: int):
  """A graph of ``nstep`` steps (None off CUDA). The step run to compile outside the capture is
  undone (the state read back), so it counts for nothing."""
  if not wp.get_device().is_cuda:
    return None
  state = read_state(d)
  mjw.step(m, d)  # compile outside the capture
  write_state(d, state)
  with wp.ScopedCapture() as cap:
    for _ in range(nstep):
      mjw.step(m, d)
  write_state(d, state)  # capturing launches nothing, but keep the state plainly the one saved
  return cap.graph


def parse_args():
  p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
  p.add_argument("--scene", default=None, help="default: pile_256_128.xml, or the checkpoint's with --resume")
  p.add_argument("--nworld", type=int, default=None, help="default 1024, or the checkpoint's with --resume")
  p.add_argument("--steps", type=int, default=100_000, help="steps in all (over every segment)")
  p.add_argument("--chunk", type=int, default=500)
  p.add_argument("--minutes", type=float, default=None,
                 help="stop before a chunk that would end this long after the start (setup and compile included)")
  p.add_argument("--nconmax", type=int, default=None,
                 help="contacts per world (default: 2 x MuJoCo C's after 500 steps, or the checkpoint's)")
  p.add_argument("--json", default=None)
  p.add_argument("--save", default=None, help="write a checkpoint (.npz) here when this segment stops")
  p.add_argument("--save-every", type=int, default=0, help="also write it every N chunks (0: only at the end)")
  p.add_argument("--save-max-mib", type=float, default=15.0,
                 help="leave qacc_warmstart out if the state arrays would pass this size (uncompressed)")
  p.add_argument("--save-failing", default=None,
                 help="write here the state and controls at the start of the chunk before the first failing "
                      "one (a geom stuck in the ground fails at the second of two chunk ends), to replay it")
  p.add_argument("--resume", default=None, help="continue the soak saved in this checkpoint")
  p.add_argument("--ctrl-noise", type=float, default=0.0,
                 help="each chunk, controls = the keyframe's + uniform noise of this amplitude "
                 "(energy then not judged)")
  p.add_argument("--reset-every", type=int, default=0,
                 help="reset each world (masked reset_data, to the keyframe) every N chunks, staggered (0: never)")
  return p.parse_args()


def scene_path(args, meta) -> str:
  """The scene to load: --scene, else the checkpoint's (here, or by name in scenes/), else the default."""
  if args.scene:
    return args.scene
  if meta is None:
    return os.path.join(HERE, "scenes", "pile_256_128.xml")
  if os.path.exists(meta["scene_path"]):
    return meta["scene_path"]
  return os.path.join(HERE, "scenes", meta["scene"])


def main():
  start = time.perf_counter()
  args = parse_args()
  wp.config.log_level = wp.LOG_WARNING
  try:
    meta, state = load_checkpoint(args.resume) if args.resume else (None, None)
    scene = scene_path(args, meta)
    if not os.path.exists(scene):
      make_scenes.main()
    sha = scene_sha256(scene)
    if meta is not None:
      check_resume(meta, args.resume, scene, sha, args.nworld, args.nconmax)
  except CheckpointError as e:
    fail(str(e))
  versions = {"warp": wp.__version__, "mujoco": mujoco.__version__}
  if meta is not None and meta["versions"] != versions:
    print(f"soak: warning: {args.resume} was written with {meta['versions']}, this run has {versions}", file=sys.stderr)

  mjm = mujoco.MjModel.from_xml_path(scene)
  mjm.opt.enableflags |= mujoco.mjtEnableBit.mjENBL_ENERGY
  m = mjw.put_model(mjm)
  install(mjm, m)
  if meta is None:
    nworld = args.nworld or 1024
    d, ref = fresh_start(mjm, m, nworld, args.nconmax)
    hist = new_history()
  else:
    nworld, ref, hist = meta["nworld"], meta["ref"], meta["history"]
    d = resume_start(mjm, m, meta, state)
    print(f"resumed {args.resume}: step {hist['steps']}, {hist['segments']} segment(s) before, "
          f"warm start {'restored' if WARMSTART in state else 'not saved'}", flush=True)
  limit = None if args.ctrl_noise else ref["energy_bound"]
  collider = get_collider(m)
  ground = Ground(mjm)
  episodes = Episodes(mjm, m, nworld, args.ctrl_noise, args.reset_every)
  hist["segments"] += hist["steps"] < args.steps  # a resume with nothing left to run adds no segment
  segment, steps0, seconds0 = hist["segments"], hist["steps"], hist["seconds"]

  def checkpoint_meta():
    return {"format": FORMAT, "scene": os.path.basename(scene), "scene_path": os.path.abspath(scene),
            "scene_sha256": sha, "nworld": nworld, "steps_asked": args.steps, "ref": ref, "history": hist,
            "versions": {"warp": wp.__version__, "mujoco": mujoco.__version__}}

  def run(n: int):
    if graph is not None and n == args.chunk:
      wp.capture_launch(graph)
    else:
      for _ in range(n):
        mjw.step(m, d)

  graph = capture(m, d, args.chunk) if hist["steps"] < args.steps else None
  t0 = time.perf_counter()
  reason, slowest, saved = "steps", 0.0, None
  before = set()  # (world, geom) in the ground at the last chunk end (not carried over a resume)
  starts = []  # (step, state and controls) at the last two chunks' starts, for --save-failing
  failing_saved = False
  while hist["steps"] < args.steps:
    elapsed = time.perf_counter() - t0
    if args.minutes and time.perf_counter() - start + slowest > 60 * args.minutes:
      reason = "time limit"
      break
    n = min(args.chunk, args.steps - hist["steps"])
    episodes.drive(d)
    if args.save_failing:
      starts = (starts + [(hist["steps"], read_state(d, STATE + (WARMSTART, "ctrl")))])[-2:]
    run(n)
    hist["steps"] += n
    row, bad, through = check_chunk(d, collider, nworld, limit, ground, before)
    now = time.perf_counter() - t0
    slowest = max(slowest, now - elapsed)
    hist["seconds"] = seconds0 + now
    row = {"step": hist["steps"], "segment": segment, "seconds": hist["seconds"], **row}
    record(hist, row, bad)
    if bad and args.save_failing and not failing_saved:
      step, state = starts[0]
      save_state(args.save_failing, state, dict(checkpoint_meta(), start_step=step, failed_at=hist["steps"], what=bad))
      failing_saved = True
      print(f"saved the state at step {step}, a chunk before the first failing chunk's end, to {args.save_failing}",
            flush=True)
    reset = episodes.reset(d, hist["chunks"], ground.off_terrain(d))
    before = {(w, g) for w, g in through if not reset[w]}
    print(f"step {row['step']:7d}  {row['seconds']:7.1f} s  energy max {row['energy_max']:.5g}"
          f" mean {row['energy_mean']:.5g}  contacts/world {row['contacts_per_world']:.1f}  {'; '.join(bad) or 'ok'}",
          flush=True)
    if args.save and args.save_every and hist["chunks"] % args.save_every == 0:
      saved = dict(save_checkpoint(args.save, d, checkpoint_meta(), args.save_max_mib), step=hist["steps"])
  if args.save and (saved is None or saved["step"] != hist["steps"]):
    saved = dict(save_checkpoint(args.save, d, checkpoint_meta(), args.save_max_mib), step=hist["steps"])
  if saved:
    print(f"saved {saved['path']} ({saved['mib']:.2f} MiB, warm start "
          f"{'saved' if saved['warmstart_saved'] else 'left out'})")

  steps, failures = hist["steps"], hist["failures"]
  complete = steps >= args.steps
  contacts = [row["contacts_per_world"] for row in hist["trace"]]
  late = contacts[len(contacts) // 2:]  # the pile has settled by the second half
  report = {"device": bench.device_name(), "scene": os.path.basename(scene), "nworld": nworld,
            "steps": steps, "world_steps": steps * nworld, "nan": hist["nonfinite_chunks"],
            "overflow": int(bool(hist["overflow_bits"] or hist["dropped_pairs_max"])),
            "energy_max_seen": hist["energy_max_seen"],
            "contacts_per_world_second_half": {"min": min(late), "mean": float(np.mean(late)), "max": max(late)}
            if late else None,
            "steps_run": steps, "steps_asked": args.steps, "stopped_by": reason, "chunk": args.chunk,
            "energy_initial_max": ref["energy_initial_max"], "energy_bound": ref["energy_bound"],
            "energy_judged": limit is not None, "ctrl_noise": args.ctrl_noise, "reset_every": args.reset_every,
            "worlds_reset_this_segment": episodes.resets,
            "geoms_through_ground_max": max((r.get("geoms_through_ground", 0) for r in hist["trace"]), default=0),
            "geoms_through_ground_total": sum(r.get("geoms_through_ground", 0) for r in hist["trace"]),
            "geoms_stuck_total": sum(r.get("geoms_stuck", 0) for r in hist["trace"]),
            "worlds_off_terrain": sum(r.get("worlds_off_terrain", 0) for r in hist["trace"]),
            "failures": failures,
            "passed": not failures, "versions": {"warp": wp.__version__, "mujoco": mujoco.__version__},
            "complete": complete, "segments": segment, "steps_this_segment": steps - steps0,
            "seconds_this_segment": hist["seconds"] - seconds0, "seconds_total": hist["seconds"],
            "nconmax": ref["nconmax"], "scene_sha256": sha, "potential_span": ref["potential_span"],
            "resumed_from": args.resume, "saved_to": saved, "summary": summary(hist, ref), "trace": hist["trace"]}
  print(f"{steps} of {args.steps} steps x {nworld} worlds over {segment} segment(s):"
        f" {'passed' if not failures else f'{len(failures)} failing chunks'} (stopped by {reason};"
        f" {'complete' if complete else 'not complete'})")
  if args.json:
    with open(args.json, "w") as f:
      json.dump(report, f, indent=1)
    print("wrote", args.json)
  sys.exit(0 if not failures else 1)


if __name__ == "__main__":
  main()
