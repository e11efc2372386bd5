"""The stage contract: what the Collider holds of a step-time stage, and how it runs one."""

from typing import Any
from typing import Protocol


class Stage(Protocol):
  """A step-time stage (docs/architecture.md, "The stage contract").

  Made at install by the Collider from the model-time facts it reads (its own typed attributes:
  which pairs the model has, the data install built), it owns its kernels, makes its per-Data
  buffers when a Data first collides, and launches its kernels for one collision call. ``st`` is
  the Data's state (collider.DataState): every stage's buffers under the stage's name, the warm
  start cache, the contact quota and the call's ``awake_prev``."""

  def make_buffers(self, d, st) -> Any:
    """This stage's buffers for Data ``d`` (None: it has none); those of the stages before it in
    the pipeline are already in ``st``."""

  def launch(self, m, d, st) -> None:
    """The stage's launches for one collision call on ``d``."""
