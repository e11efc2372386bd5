"""Notes on Warp's kernel compilation at first use: which modules compile, how many, how long.

Warp compiles a kernel module on its first launch on a device unless its kernel cache holds the
module's binary (a file named after a hash of the module's code and options, in
``wp.config.kernel_cache_dir``). With an empty cache that takes about a minute on a CPU for a model's
collision stage and step, several minutes on a GPU, and Warp prints nothing while it works (or, at
its default log level, a line per module afterwards). So the plugin writes notes on logger
``mjx_supportfield`` at INFO, from ``install`` to the end of each installed model's first step::

  first use on cpu: Warp compiles 9 kernel modules for the plugin's first collision (roughly 45 s) ...
    [1/9] mjx_supportfield.stages.stage_ends
    ...
    9 modules compiled in 37 s; later runs load them from Warp's kernel cache

The plugin's first collision is first run as a plan: its launches are skipped (Warp's
``Module.load`` answers None, on which ``wp.launch`` returns) and the modules that would compile are
counted; then it runs. Everything cached: nothing is written. The watch (a wrapper around Warp's
``Module.load``, which costs each launch a few microseconds) is removed at the next collision
after a first one, so later steps run exactly as without it.

Silence the notes with ``logging.getLogger("mjx_supportfield").setLevel(logging.WARNING)``. While
the application has configured no logging, they go to stderr; else through its handlers.
"""

import contextlib
import logging
import os
import sys
import threading
import time
import weakref
from concurrent.futures import ThreadPoolExecutor

import warp as wp
from warp._src import context as wp_context

from mjx_supportfield.launch import prebuilt

logger = logging.getLogger("mjx_supportfield")
if logger.level == logging.NOTSET:
  logger.setLevel(logging.INFO)

# Without a count (stages that are not planned: MuJoCo Warp's step has dozens of small modules), a
# module's line is written only this long after the last one; the summary counts them all.
_QUIET_SECONDS = 5.0

# Rough build time of one of the plugin's kernel modules with an empty cache, for the estimate in
# the first note: LLVM builds for the CPU take seconds each, NVRTC builds for a GPU up to minutes
# (the narrow phase's).
_ROUGH_SECONDS_PER_MODULE = {"cpu": 5.0, "cuda": 45.0}


class _Fallback(logging.Handler):
  """Writes the notes to stderr while nothing else would show them (no handler configured)."""

  def emit(self, record):
    if logging.getLogger().handlers or any(h is not self for h in logger.handlers):
      return  # the application's logging (or the command line's handler) shows them
    try:
      sys.stderr.write(f"mjx_supportfield: {self.format(record)}\n")
      sys.stderr.flush()
    except Exception:
      self.handleError(record)


if not any(isinstance(h, _Fallback) for h in logger.handlers):
  logger.addHandler(_Fallback())


def _build_workers() -> int:
  """Threads that compile a first collision's modules side by side: ``MJX_SUPPORTFIELD_BUILD_THREADS``
  where set (1: one after another), else one a core up to 8 (each NVRTC build holds about a GiB
  of memory). Warp's own ``load_module_max_workers`` is left to ``wp.load_module``: its default
  there is one after another."""
  value = os.environ.get("MJX_SUPPORTFIELD_BUILD_THREADS", "")
  if value.strip():
    try:
      return max(1, int(value))
    except ValueError:
      logger.warning("MJX_SUPPORTFIELD_BUILD_THREADS=%r is not an integer; building with one thread a core", value)
  return max(1, min(os.cpu_count() or 1, 8))


def _rough(seconds: float) -> str:
  return f"roughly {seconds:.0f} s" if seconds < 90 else f"roughly {seconds / 60:.0f} min"


def _describe(module) -> str:
  """A module's name for people: its Python module (with the support mode, for a stage's module
  of one mode: ``<module>.<mode>``), and for a one-kernel module that a factory made (Warp names
  those ``<factory>__locals__<kernel>_<hash>``) the factory and the kernel."""
  kernels = list(module.kernels.values())
  if len(kernels) == 1 and not module.name.startswith(kernels[0].func.__module__):
    func = kernels[0].func
    return f"{func.__module__}.{func.__qualname__.replace('.<locals>', '')}"
  return module.name


def _will_compile(module, device, block_dim) -> bool:
  """Whether loading ``module`` on ``device`` builds it: it is not loaded, and Warp's kernel cache
  lacks its binary or metadata (the test ``Module._compile`` makes)."""
  try:
    device = wp.get_device(device)
    block_dim = module.options["block_dim"] if block_dim is None else block_dim
    if (device.context, block_dim) in module.execs:
      # loaded: a launch's usual case, kept cheap (a module changed after loading, which Warp
      # rebuilds, goes unnoted)
      return False
    if module.failed_builds.get((device.context, block_dim)) is not None:
      return False  # Warp raises the recorded error
    if not wp.config.cache_kernels:
      return True
    folder = os.path.join(wp.config.kernel_cache_dir, module.get_module_identifier(block_dim))
    binary = module._get_compile_output_name(device, block_dim=block_dim)
    meta = module._get_meta_name(block_dim=block_dim)
    return not (os.path.exists(os.path.join(folder, binary)) and os.path.exists(os.path.join(folder, meta)))
  except Exception:  # a Warp that works otherwise: no notes rather than a failed launch
    return False


class _Stage:
  """Compiles within one stage (install, the plugin's first collision, ...), noted as they come."""

  def __init__(self, label: str, planned: int = 0, workers: int = 1):
    self.label, self.planned, self.workers = label, planned, workers
    self.count, self.t0, self.device, self.last_line = 0, None, None, 0.0
    self.prebuilt = 0  # modules loaded from a pack of prebuilt binaries instead (prebuilt.py)
    self.seen = set()  # names noted: a factory's kernel built twice is another variant

  def begin(self, device):
    """The stage's first note: what compiles, and roughly how long it takes."""
    if self.t0 is not None:
      return
    self.t0, self.device = time.perf_counter(), wp.get_device(device)
    kind = "cuda" if self.device.is_cuda else "cpu"
    if self.planned:
      what = f"{self.planned} kernel module{'s' if self.planned > 1 else ''} for {self.label}"
      rounds = -(-self.planned // self.workers)  # modules one after another in the busiest thread
      side = f", {self.workers} at a time" if self.workers > 1 else ""
      rough = f" ({_rough(rounds * _ROUGH_SECONDS_PER_MODULE[kind])}{side})"
    else:
      what, rough = f"kernels for {self.label}", ""
    logger.info("first use on %s: Warp compiles %s%s; they are not in its kernel cache yet (%s)", self.device.alias,
                what, rough, wp.config.kernel_cache_dir)

  def note(self, module, device, done: bool = False):
    """A module's line: as it starts compiling, or (``done``) once it is built."""
    self.begin(device)
    self.count += 1
    total = f"/{self.planned}" if self.planned >= self.count else ""
    name = _describe(module)
    variant = ", another variant" if name in self.seen else ""
    self.seen.add(name)
    elapsed = time.perf_counter() - self.t0
    if self.planned or self.count == 1 or elapsed - self.last_line >= _QUIET_SECONDS:
      self.last_line = elapsed
      logger.info("  [%d%s] %s%s%s%s", self.count, total, name, variant, " built" if done else "",
                  f" ({elapsed:.0f} s so far)" if elapsed >= 1 else "")

  def close(self):
    if self.prebuilt:
      logger.info("%s: %d kernel module%s loaded prebuilt", self.label, self.prebuilt, "s" if self.prebuilt > 1 else "")
    if self.count:
      seconds = time.perf_counter() - self.t0
      logger.info("  %d module%s compiled in %.0f s; later runs load %s from Warp's kernel cache", self.count,
                  "s" if self.count > 1 else "", seconds, "them" if self.count > 1 else "it")
    if self.count or self.prebuilt:
      _HISTORY.append({"stage": self.label, "device": (self.device or wp.get_device()).alias, "modules": self.count,
                       "seconds": time.perf_counter() - self.t0 if self.count else 0.0, "prebuilt": self.prebuilt})


_HISTORY = []  # the stages that compiled, in order (compile_history)


def compile_history() -> list[dict]:
  """Each stage of this process that compiled kernel modules, in order: its label (``"install
  (support fields and SDFs)"``, ``"MuJoCo Warp's first step"``, ``"the plugin's first collision"``,
  a command's), the device, how many modules and the seconds from its first compile to its end
  (``benchmarks/first_step.py`` splits a first step's time with it)."""
  return [dict(h) for h in _HISTORY]


class _Watch:
  """Wraps Warp's ``Module.load`` while first uses may compile; see the module docstring."""

  def __init__(self):
    self.original = None  # Warp's Module.load while wrapped
    self.holders = []  # labels of the open announce_compiles blocks
    self.pending = weakref.WeakSet()  # installed colliders before their first collision
    self.stage = None
    self.planning = threading.local()  # .plan: modules the planned run would compile, by id
    self.lock = threading.RLock()

  # --- the wrapper -----------------------------------------------------------------------------

  def load(self, module, device=None, block_dim=None, *args, **kwargs):
    plan = getattr(self.planning, "plan", None)
    if plan is not None:  # this thread plans a first collision
      if not args and not kwargs and self.must_build(module, device, block_dim):
        plan[(id(module), block_dim)] = (module, device, block_dim)
      return None  # wp.launch returns without launching
    if not args and not kwargs and self.must_build(module, device, block_dim):
      with self.lock:
        self.stage.note(module, device)
    return self.original(module, device, block_dim, *args, **kwargs)

  def must_build(self, module, device, block_dim) -> bool:
    """Whether loading ``module`` compiles it: not in Warp's kernel cache, nor in a pack of
    prebuilt binaries (prebuilt.place puts it in the cache, counted in the stage's note)."""
    if not _will_compile(module, device, block_dim):
      return False
    placed = prebuilt.place(module, device, block_dim)
    with self.lock:
      if self.stage is None:
        self.stage = _Stage(self.holders[-1] if self.holders else "MuJoCo Warp's first step")
      if placed:
        self.stage.prebuilt += 1
    return not placed

  def start(self):
    if self.original is None:
      self.original = wp_context.Module.load
      watch = self

      def load(module, device=None, block_dim=None, *args, **kwargs):
        return watch.load(module, device, block_dim, *args, **kwargs)

      wp_context.Module.load = load
    _set_active(True)

  def stop(self):
    """Unwraps Warp's Module.load unless a block asks for notes; models still to collide keep
    the dispatcher routing through ``collide``, which wraps it again for their first collision."""
    if not self.holders:
      self.end_stage()
      if self.original is not None:
        wp_context.Module.load = self.original
        self.original = None
    _set_active(self.original is not None or len(self.pending) > 0)

  def end_stage(self):
    with self.lock:
      if self.stage is not None:
        self.stage.close()
      self.stage = None

  # --- the plugin's first collision ------------------------------------------------------------

  def first_collision(self, collider, m, d, awake_prev):
    self.end_stage()  # MuJoCo Warp's kinematics before it
    with self.lock:
      self.stage = _Stage("the plugin's first collision")  # counts the modules the plan finds prebuilt
    planned = self.plan_run(collider, m, d, awake_prev)
    with self.lock:
      self.stage.planned = len(planned)
      self.stage.workers = min(len(planned), _build_workers()) if len(planned) > 1 else 1
    try:
      self.build(planned)
      collider.collision(m, d, awake_prev)
    finally:
      self.end_stage()

  def plan_run(self, collider, m, d, awake_prev) -> list:
    """(module, device, block_dim) of each module the first collision would compile: a run whose
    launches are skipped. Not while a graph is captured (the plan's host-side work would be
    recorded), nor with flexes or a contact filter callback (host-side work that is not only
    launches)."""
    if collider.device.is_capturing or m.nflex or getattr(m.callback, "contactfilter", None):
      return []
    plan = self.planning.plan = {}
    try:
      collider.collision(m, d, awake_prev)
      return list(plan.values())
    except Exception:  # the real run raises it again, with nothing skipped
      logger.debug("planning the first collision failed", exc_info=True)
      return []
    finally:
      self.planning.plan = None

  def build(self, planned: list):
    """Compiles the planned modules side by side (Warp's compilers run outside the GIL, as in
    ``wp.force_load``), each noted when done: the first collision then waits for its longest
    module, not for the sum. Errors are left to the collision's own loads, which raise them."""
    if len(planned) < 2:
      return  # the collision's launch compiles it, noted by the wrapper

    def load(item):
      module, device, block_dim = item
      self.original(module, device, block_dim)
      with self.lock:
        if self.stage is not None:
          self.stage.note(module, device, done=True)

    with self.lock:
      self.stage.begin(planned[0][1])
    try:
      with ThreadPoolExecutor(max_workers=self.stage.workers) as pool:
        list(pool.map(load, planned))
    except Exception:
      logger.debug("building the planned modules side by side failed", exc_info=True)


_watch = _Watch()

# True while Warp's Module.load is wrapped or an installed model has yet to collide: the dispatcher
# then routes collisions through ``collide``
active = False


def planning() -> bool:
  """Whether this thread runs a first collision as a plan (launches skipped, modules not
  loaded): host code that would load a module for other reasons (occupancy queries) skips it."""
  return getattr(_watch.planning, "plan", None) is not None


def _set_active(value: bool):
  global active
  active = value


def arm(collider) -> None:
  """Called by ``install``: notes compiles until ``collider``'s first collision is done."""
  with _watch.lock:
    _watch.pending.add(collider)
    _watch.start()


def disarm(collider) -> None:
  """Called by ``uninstall``: ``collider`` will not collide again."""
  with _watch.lock:
    _watch.pending.discard(collider)
    _watch.stop()


def collide(collider, m, d, awake_prev=None) -> None:
  """``collider.collision`` while the watch is on: the first collision of an installed model is
  planned and its compiles counted; a later one (the next step) ends the wrapper around Warp's
  Module.load."""
  if collider in _watch.pending:
    with _watch.lock:
      _watch.pending.discard(collider)
      _watch.start()  # also when another model's step ended the watch
    _watch.first_collision(collider, m, d, awake_prev)
    return
  with _watch.lock:
    _watch.end_stage()  # the rest of the previous step
    # a step is over: launches stop paying for the wrapper, even while another installed model
    # has yet to collide (its first collision wraps Module.load again)
    _watch.stop()
  collider.collision(m, d, awake_prev)


@contextlib.contextmanager
def announce_compiles(label: str):
  """Within the block, notes every Warp module that compiles (as ``label`` when no plugin stage
  is under way); the command line wraps each command in one."""
  with _held(label, end_current=False):
    yield


@contextlib.contextmanager
def stage(label: str):
  """Within the block, compiles are noted under ``label`` (``install`` uses it)."""
  with _held(label, end_current=True):
    yield


@contextlib.contextmanager
def _held(label: str, end_current: bool):
  """Keeps the watch on, noting compiles under ``label``, for the block; ``end_current`` first
  closes the stage under way, so its summary is written before this one's notes."""
  with _watch.lock:
    if end_current:
      _watch.end_stage()
    _watch.holders.append(label)
    _watch.start()
  try:
    yield
  finally:
    with _watch.lock:
      _watch.end_stage()
      _watch.holders.remove(label)
      _watch.stop()
