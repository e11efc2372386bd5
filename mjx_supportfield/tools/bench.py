"""Speed of the plugin vs stock MuJoCo Warp: collision stage and whole step, graph-captured."""

import dataclasses
import json
import os
import platform
import sys
import time
from typing import Optional

import mujoco
import mujoco_warp as mjw
import numpy as np
import warp as wp
from mujoco_warp._src import collision_driver
from mujoco_warp._src.types import OverflowType

from mjx_supportfield.driver import install
from mjx_supportfield.launch import first_use
from mjx_supportfield.options import Options
from mjx_supportfield.tools.model_file import load_model


@dataclasses.dataclass
class Row:
  """One timing: scene, nworld, impl ("plugin" | "stock"), stage ("collision" | "step").

  A collision row also carries ``step_minus_rest_ms``: the step minus the step without collision,
  and ``frozen_ms``: the collision stage repeated on the settled state (no step between calls).
  """

  scene: str
  nworld: int
  impl: str
  stage: str
  ms: float
  contacts_per_world: float
  step_minus_rest_ms: Optional[float] = None
  frozen_ms: Optional[float] = None
  nconmax: Optional[int] = None  # the room both implementations were timed with
  overflow: int = 0  # MuJoCo Warp's OverflowType bits raised while timing (0: none)


class Progress:
  """A progress indicator on stderr (no dependency; compile steps take minutes)."""

  def __init__(self, total: int):
    self.total, self.done, self.t0 = total, 0, time.perf_counter()

  def step(self, what: str):
    self.done += 1
    width = 30
    filled = int(width * self.done / self.total)
    elapsed = time.perf_counter() - self.t0
    # a line each (not one redrawn line): notes on compiling kernels come between them
    sys.stderr.write(f"[{'#' * filled}{'.' * (width - filled)}] {self.done}/{self.total} {elapsed:6.0f}s {what}\n")
    sys.stderr.flush()


def settled_state(mjm: mujoco.MjModel, settle_steps: int, keyframe: Optional[int] = None) -> mujoco.MjData:
  """MuJoCo C state after ``settle_steps`` steps from qpos0 (as ``compare`` samples states), or
  from keyframe ``keyframe`` (a scene whose qpos0 is no physical state: robots placed in the
  ground, to stand where their keyframe puts them)."""
  mjd = mujoco.MjData(mjm)
  if keyframe is not None:
    if not 0 <= keyframe < mjm.nkey:
      raise ValueError(f"keyframe {keyframe}: the model has {mjm.nkey} keyframe(s)")
    mujoco.mj_resetDataKeyframe(mjm, mjd, keyframe)
  for _ in range(settle_steps):
    mujoco.mj_step(mjm, mjd)
  mujoco.mj_forward(mjm, mjd)
  return mjd


def _time_graph(fn, launches: int) -> float:
  """Milliseconds per launch of ``fn`` captured in a CUDA graph (or called, on the CPU)."""
  device = wp.get_device()
  if device.is_cuda:
    with wp.ScopedCapture() as capture:
      fn()
    wp.capture_launch(capture.graph)  # warm
    wp.synchronize()
    t = time.perf_counter()
    for _ in range(launches):
      wp.capture_launch(capture.graph)
    wp.synchronize()
  else:
    fn()
    t = time.perf_counter()
    for _ in range(launches):
      fn()
    wp.synchronize()
  return (time.perf_counter() - t) / launches * 1e3


_STEPS_PER_GRAPH = 10


def _time_collision_in_steps(m, d, launches: int) -> Optional[float]:
  """GPU milliseconds of the collision stage per step, inside graph-captured steps: timing events
  recorded around every collision call that ``mjw.step`` makes (through the module attribute
  MuJoCo Warp calls, where ``install`` puts its dispatcher). On the CPU: None."""
  if not wp.get_device().is_cuda:
    return None
  calls = []
  inner = collision_driver.collision

  def timed(m_, d_, awake_prev=None):
    start, end = wp.Event(enable_timing=True), wp.Event(enable_timing=True)
    wp.record_event(start)
    inner(m_, d_, awake_prev)
    wp.record_event(end)
    calls.append((start, end))

  collision_driver.collision = timed
  try:
    with wp.ScopedCapture() as capture:
      for _ in range(_STEPS_PER_GRAPH):
        mjw.step(m, d)
  finally:
    collision_driver.collision = inner
  return replay_events(capture.graph, calls, launches)


def replay_events(graph, calls: list, launches: int) -> float:
  """Milliseconds per timed call: replays ``graph`` (one warm-up, then about ``launches`` calls)
  and sums the (start, end) event pairs it records."""
  wp.capture_launch(graph)  # warm
  total = 0.0
  replays = max(1, launches // len(calls))
  for _ in range(replays):
    wp.capture_launch(graph)
    wp.synchronize()  # an event holds its last replay's time only
    total += sum(wp.get_event_elapsed_time(start, end) for start, end in calls)
  return total / (replays * len(calls))


def _time_collision_frozen(mjm, mjd, m, nworld: int, nconmax: int, njmax: int, launches: int) -> float:
  """Milliseconds per collision call repeated on the settled state ``mjd`` (fresh Data, nothing
  steps between calls): CUDA events around each call in a captured graph, as inside steps; on the
  CPU the wall time. The plugin's warm start holds the answer from the second call on, so this
  flatters it; it is the figure beside the one inside evolving steps."""
  d = mjw.put_data(mjm, mjd, nworld=nworld, nconmax=nconmax, njmax=njmax)
  mjw.collision(m, d)  # the plugin's per-Data state, outside the graph
  wp.synchronize()
  if not wp.get_device().is_cuda:
    return _time_graph(lambda: mjw.collision(m, d), launches)
  calls = []
  with wp.ScopedCapture() as capture:
    for _ in range(_STEPS_PER_GRAPH):
      start, end = wp.Event(enable_timing=True), wp.Event(enable_timing=True)
      wp.record_event(start)
      mjw.collision(m, d)
      wp.record_event(end)
      calls.append((start, end))
  return replay_events(capture.graph, calls, launches)


def scene_name(path: str) -> str:
  """A scene's name: its file name, or its folder's for MuJoCo Warp's ``.../aloha_pot/scene.xml``."""
  scene = os.path.basename(path).removesuffix(".xml").removesuffix(".mjb")
  return os.path.basename(os.path.dirname(path)) if scene == "scene" else scene


def bench_scene(path: str, nworlds: list[int], launches: int, settle_steps: int, nconmax: Optional[int],
                options: Optional[Options], progress: Optional[Progress] = None,
                keyframe: Optional[int] = None) -> list[Row]:
  """Times both implementations on one scene for each nworld, from its settled state
  (settled_state: ``settle_steps`` of MuJoCo C from qpos0 or from keyframe ``keyframe``).

  Both get the same room (``nconmax``, ``njmax``). With ``nconmax`` None it starts from what
  MuJoCo C finds at the settled state and doubles (both timed again) while either implementation
  overflows its room during the timed steps, so that neither is timed dropping pairs or
  constraints; a given ``nconmax`` stays, and an overflow is reported on stderr and in the rows.
  """
  mjm = load_model(path)
  mjd = settled_state(mjm, settle_steps, keyframe)
  scene = scene_name(path)
  # room for what MuJoCo C finds at the settled state, with headroom for both implementations
  ncon = nconmax or int(1.5 * mjd.ncon) + 16
  rows = []
  for nworld in nworlds:
    for attempt in range(_ROOM_ATTEMPTS):
      pair = [time_impl(mjm, mjd, scene, nworld, impl, ncon, launches, options) for impl in ("stock", "plugin")]
      overflow = (pair[0][2] | pair[1][2]) & _ROOM_BITS
      if not overflow or nconmax is not None or attempt == _ROOM_ATTEMPTS - 1:
        break
      sys.stderr.write(f"{scene}, nworld {nworld}: overflow ({_overflow_names(overflow)}) at nconmax {ncon}; "
                       f"timing both again with {2 * ncon}\n")
      ncon *= 2
    for collision, step, bits in pair:
      if bits & _ROOM_BITS:
        sys.stderr.write(f"warning: {scene}, nworld {nworld}, {collision.impl}: overflow ({_overflow_names(bits & _ROOM_BITS)}) "
                         f"at nconmax {ncon}; its timing dropped work\n")
      rows += [collision, step]
      if progress:
        progress.step(f"{scene} nworld={nworld} {collision.impl}")
  return rows


_ROOM_ATTEMPTS = 4  # nconmax up to 8x the first guess
# the overflows of room (contacts, pairs, constraints), which more nconmax / njmax cures; the
# solver's iteration flags are not
_ROOM_BITS = int(OverflowType.NEFC | OverflowType.NJMAX_NNZ | OverflowType.BROADPHASE | OverflowType.NARROWPHASE)


def _overflow_names(bits: int) -> str:
  return ", ".join(t.name.lower() for t in OverflowType if bits & int(t))


def time_impl(mjm, mjd, scene: str, nworld: int, impl: str, ncon: int, launches: int,
                options: Optional[Options]) -> tuple[Row, Row, int]:
  """The collision row, the step row and the overflow bits raised while timing one
  implementation ("stock" or "plugin") with ``ncon`` contacts of room per world."""
  njmax = 6 * ncon + mjd.nefc
  m = mjw.put_model(mjm)
  if impl == "plugin":
    install(mjm, m, options or Options())
  d = mjw.put_data(mjm, mjd, nworld=nworld, nconmax=ncon, njmax=njmax)
  # compiles (noted; the note's watch is gone before the timing); creates the plugin's
  # per-Data state outside the graph
  with first_use.announce_compiles(f"{scene}, {impl}"):
    mjw.forward(m, d)
    mjw.step(m, d)
  wp.synchronize()
  mjw.collision(m, d)
  contacts = min(int(d.nacon.numpy()[0]), d.naconmax) / nworld
  ms_step = _time_graph(lambda: mjw.step(m, d), launches)
  # the collision stage: timed inside evolving steps (events around each collision call).
  # Timing collision calls repeated on one state would flatter the plugin: from the second
  # call on, its warm start holds the answer. Also the step minus the step without collision
  # (the contacts stay as the last step left them), which adds what the collision's output
  # changes in the rest of the step.
  ms_collision = _time_collision_in_steps(m, d, launches)
  m.opt.run_collision_detection = False
  ms_rest = _time_graph(lambda: mjw.step(m, d), launches)
  m.opt.run_collision_detection = True
  diff = ms_step - ms_rest
  overflow = int(np.bitwise_or.reduce(d.overflow.numpy()))  # MuJoCo Warp ORs the flags in, step after step
  ms_frozen = _time_collision_frozen(mjm, mjd, m, nworld, ncon, njmax, launches)
  collision = Row(scene, nworld, impl, "collision", diff if ms_collision is None else ms_collision, contacts, diff,
                  ms_frozen, ncon, overflow)
  return collision, Row(scene, nworld, impl, "step", ms_step, contacts, nconmax=ncon, overflow=overflow), overflow


def format_table(rows: list[Row]) -> str:
  """ms, million world-steps per second and stock/plugin ratio per scene, nworld and stage."""
  out = [f"{'scene':24s} {'nworld':>6s} {'stage':9s} {'stock ms':>9s} {'plugin ms':>9s} {'speed-up':>8s} "
         f"{'plugin Mws/s':>12s} {'con/world stock':>15s} {'plugin':>7s} {'step-rest: stock':>16s} {'plugin':>7s} "
         f"{'frozen: stock':>13s} {'plugin':>7s}"]
  keyed = {(r.scene, r.nworld, r.stage, r.impl): r for r in rows}
  for (scene, nworld, stage, impl), r in keyed.items():
    if impl != "plugin" or (scene, nworld, stage, "stock") not in keyed:
      continue
    s = keyed[(scene, nworld, stage, "stock")]
    line = (f"{scene:24s} {nworld:6d} {stage:9s} {s.ms:9.3f} {r.ms:9.3f} {s.ms / r.ms:7.2f}x "
            f"{nworld / r.ms / 1e3:12.2f} {s.contacts_per_world:15.1f} {r.contacts_per_world:7.1f}")
    if r.step_minus_rest_ms is not None and s.step_minus_rest_ms is not None:
      line += f" {s.step_minus_rest_ms:16.3f} {r.step_minus_rest_ms:7.3f}"
    if r.frozen_ms is not None and s.frozen_ms is not None:
      line += f" {s.frozen_ms:13.3f} {r.frozen_ms:7.3f}"
    out.append(line)
  return "\n".join(out)


def device_name() -> str:
  """The GPU's name, or "cpu" (short: benchmark scripts name their result files after it)."""
  device = wp.get_device()
  return device.name if device.is_cuda else (platform.processor() or "cpu")


def cpu_model() -> str:
  """The host CPU's model name (Linux: /proc/cpuinfo), or what ``platform`` knows."""
  try:
    with open("/proc/cpuinfo") as f:
      for line in f:
        if line.startswith("model name"):
          return line.split(":", 1)[1].strip()
  except OSError:
    pass
  return platform.processor() or platform.machine() or "unknown CPU"


def device_description() -> str:
  """The device the timings ran on, for people: the GPU's name, or the CPU's model and cores."""
  device = wp.get_device()
  if device.is_cuda:
    return device.name
  return f"CPU: {cpu_model()} ({os.cpu_count()} cores)"


# Timings average over at least this many launches: one launch's time is dominated by launch and
# synchronisation overhead and by the clock's resolution.
MIN_LAUNCHES = 100

# World counts timed when none are given. On a GPU the counts where batching pays off; on the CPU a
# step costs about nworld times one world's, so large counts take hours and tell nothing new.
GPU_WORLDS = (1024, 4096, 8192)
CPU_WORLDS = (1, 8, 64)


def default_world_counts(device=None) -> tuple:
  """World counts ``bench`` times when none are given: sized to the device (see GPU_WORLDS)."""
  device = wp.get_device(device)
  return GPU_WORLDS if device.is_cuda else CPU_WORLDS


def write_json(rows: list[Row], path: str, extra: Optional[dict] = None) -> None:
  """Writes {"device", "versions", "rows"} (plus ``extra`` keys): ``device`` names the GPU, or the
  CPU's model and cores (``device_description``)."""
  import importlib.metadata as md

  versions = {p: md.version(p) for p in ("mujoco", "mujoco-warp", "warp-lang")}
  out = {"device": device_description(), "versions": versions, "rows": [dataclasses.asdict(r) for r in rows]}
  with open(path, "w") as f:
    json.dump({**out, **(extra or {})}, f, indent=1)


ROW_KEYS = ("scene", "nworld", "impl", "stage", "ms")


def load_results(path: str) -> dict:
  """Reads a bench results file (``bench --json``) for ``plot``.

  Raises:
    ValueError: one line naming the problem: no such file, not JSON, or not a bench results file
      (a compare report, say).
  """
  if os.path.isdir(path):
    raise ValueError(f"{path} is a directory, not a bench results file (bench --json writes one)")
  try:
    with open(path) as f:
      data = json.load(f)
  except FileNotFoundError:
    raise ValueError(f"results file not found: {path}") from None
  except (OSError, UnicodeDecodeError) as e:
    raise ValueError(f"cannot read {path}: {e}") from None
  except json.JSONDecodeError as e:
    raise ValueError(f"{path} is not JSON ({e}); plot reads what 'mjx-supportfield bench --json' writes") from None
  if not isinstance(data, dict) or not isinstance(data.get("rows"), list):
    what = "a compare report" if isinstance(data, dict) and "impls" in data else "not a bench results file"
    raise ValueError(f"{path} is {what}: plot needs the \"rows\" that 'mjx-supportfield bench --json' writes")
  for i, row in enumerate(data["rows"]):
    missing = [k for k in ROW_KEYS if not isinstance(row, dict) or k not in row]
    if missing:
      raise ValueError(f"{path}: row {i} lacks {', '.join(missing)}; not a bench results file")
  return data


def plot(rows: list[dict], path: str, device: Optional[str] = None) -> None:
  """PNG of time vs nworld, both implementations, one panel per scene and stage (needs matplotlib).

  Times start at 0 ms, so that the gap between the lines reads as the ratio it is; nworld is on a
  log scale (powers of two). ``device`` (``device_description()``) goes in the title.
  """
  import matplotlib

  matplotlib.use("Agg")
  import matplotlib.pyplot as plt

  scenes = sorted({r["scene"] for r in rows})
  fig, axes = plt.subplots(len(scenes), 2, figsize=(10, 3.2 * len(scenes) + 0.4), squeeze=False)
  for i, scene in enumerate(scenes):
    for j, stage in enumerate(("collision", "step")):
      ax = axes[i][j]
      for impl, style in (("stock", "o--"), ("plugin", "s-")):
        pts = sorted((r["nworld"], r["ms"]) for r in rows if r["scene"] == scene and r["stage"] == stage and r["impl"] == impl)
        if pts:
          ax.plot([p[0] for p in pts], [p[1] for p in pts], style, label=impl)
      ax.set_xscale("log", base=2)
      ax.set_ylim(bottom=0)
      ax.set_title(f"{scene}: {stage}")
      ax.set_xlabel("nworld (log scale)")
      ax.set_ylabel("ms per step")
      ax.legend()
  if device:
    fig.suptitle(f"mjx_supportfield vs stock MuJoCo Warp on {device}")
  fig.tight_layout()
  fig.savefig(path, dpi=100)
