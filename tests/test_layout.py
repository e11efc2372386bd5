"""The package's wings (docs/architecture.md): each module imports only from its own wing or the
wings below it, so the import graph has no cycles and no back-arrows; the public face re-exports
what users call; nothing in the package reads the source tree's models/."""

import ast
import os

import pytest
from conftest import ROOT

import mjx_supportfield

PACKAGE = os.path.join(ROOT, "mjx_supportfield")
# lowest first: a module may import from its own layer and the ones before it
LAYERS = [
  {"mjx_supportfield.types", "mjx_supportfield.options"},
  {"mjx_supportfield.geometry"},
  {"mjx_supportfield.launch"},
  {"mjx_supportfield.stages"},
  {"mjx_supportfield.collider", "mjx_supportfield.stats", "mjx_supportfield.driver", "mjx_supportfield"},
  {"mjx_supportfield.tools", "mjx_supportfield.__main__"},
]


def _modules() -> dict:
  """{dotted module name: source path} of every module of the package."""
  out = {}
  for folder, _, files in os.walk(PACKAGE):
    for f in files:
      if f.endswith(".py"):
        rel = os.path.relpath(os.path.join(folder, f), ROOT)[:-3].replace(os.sep, ".")
        out[rel.removesuffix(".__init__")] = os.path.join(folder, f)
  return out


def _layer(name: str) -> int:
  for i, layer in enumerate(LAYERS):
    if any(name == w or name.startswith(w + ".") for w in layer if w != "mjx_supportfield"):
      return i
  if name == "mjx_supportfield":
    return 4
  raise AssertionError(f"{name} is in no wing of tests/test_layout.py")


def _imports(path: str) -> set:
  """The package's modules that the file imports (at any depth of the file)."""
  found = set()
  for node in ast.walk(ast.parse(open(path).read())):
    if isinstance(node, ast.ImportFrom) and node.module and node.module.startswith("mjx_supportfield"):
      for alias in node.names:  # a module (from mjx_supportfield.stages import heightfield), or a name of one
        sub = f"{node.module}.{alias.name}"
        found.add(sub if sub in _modules() else node.module)
    elif isinstance(node, ast.Import):
      found |= {a.name for a in node.names if a.name.startswith("mjx_supportfield")}
  return found


def test_every_import_points_down_or_across():
  back = []
  for name, path in _modules().items():
    for target in _imports(path):
      if _layer(target) > _layer(name):
        back.append(f"{name} -> {target}")
  assert not back, back


def test_no_import_cycles():
  graph = {name: {t for t in _imports(path) if t in _modules() and t != name} for name, path in _modules().items()}
  graph = {n: {t for t in ts if not n.startswith(t + ".")} for n, ts in graph.items()}  # a package's own __init__
  state = {}

  def visit(n, stack):
    state[n] = 1
    for t in graph.get(n, ()):
      if state.get(t) == 1:
        pytest.fail("import cycle: " + " -> ".join(stack + [n, t]))
      if not state.get(t):
        visit(t, stack + [n])
    state[n] = 2

  for n in graph:
    if not state.get(n):
      visit(n, [])


def test_public_face():
  """The names users call, from the package itself."""
  for name in ("Options", "install", "uninstall", "collision", "get_collider", "Collider", "CollisionStats"):
    assert name in mjx_supportfield.__all__ and getattr(mjx_supportfield, name) is not None
  assert callable(mjx_supportfield.install)


def test_package_reads_no_source_tree_models():
  """Scenes and measures that read the repository's models/ live in benchmarks/scenelib, outside
  the installed package."""
  for name, path in _modules().items():
    assert '"models"' not in open(path).read(), name
