"""Resting contacts stay still under the plugin for 2000 mjw.step calls (issue #4).

Scenes: models/resting.xml (a box, a cylinder on its end and the convex hull convex1 on a plane,
plus a mesh cube on a mesh cube, the pair that goes through MPR and multi-contact) and
models/box_stack.xml (five stacked cubes). The measuring code is scenelib.stability's, with
which benchmarks/stability.py prints the same figures for the plugin, stock MuJoCo Warp and MuJoCo C.

Drift is the largest distance of a body from where it was at step SETTLE (200; the scenes
start with 1 mm overlaps, pushed out within the first ~100 steps) until step 2000. Contact
motion is, for every contact, the distance to the nearest contact of the same geom pair one
step earlier, over the same window. Failure messages quote MuJoCo C's figure on the same scene.
"""

import mujoco
import pytest

from scenelib import stability

pytestmark = pytest.mark.slow  # whole trajectories

NSTEP = 2000
SETTLE = 200
PLANE_BODIES = ("box", "cylinder", "convex")
MESH_BODIES = ("meshcube0", "meshcube1")

# the plugin's multi-contact on the mesh cube on the mesh cube (benchmarks/README.md, Stability)
def _run(scene):
  mjm = mujoco.MjModel.from_xml_path(stability.model_path(scene))
  names = [mujoco.mj_id2name(mjm, mujoco.mjtObj.mjOBJ_GEOM, i) for i in range(mjm.ngeom)]
  plugin = stability.measure(stability.simulate(scene, "plugin", NSTEP, mjm=mjm), SETTLE, names)
  ref = stability.measure(stability.simulate(scene, "mujoco", NSTEP, mjm=mjm), SETTLE, names)
  return plugin, ref


@pytest.fixture(scope="module")
def resting():
  """(plugin figures, MuJoCo C figures) on models/resting.xml."""
  return _run("resting")


@pytest.fixture(scope="module")
def stack():
  """(plugin figures, MuJoCo C figures) on models/box_stack.xml."""
  return _run("box_stack")


def _drift(figures, body):
  plugin, ref = figures
  got, want = plugin["bodies"][body]["drift"], ref["bodies"][body]["drift"]
  assert got < stability.MAX_DRIFT, f"{body}: drift {got:.2e} m after step {SETTLE} (MuJoCo C {want:.2e} m)"


def _motion(figures, pair):
  plugin, ref = figures
  rec = plugin["pairs"][pair]
  want = ref["pairs"].get(pair, {}).get("max_motion", float("nan"))
  assert rec["max_motion"] < stability.MAX_CONTACT_MOTION, (
    f"{pair}: a contact moved {rec['max_motion']:.2e} m in one step (step {rec['step']}; MuJoCo C {want:.2e} m)"
  )


def _no_flicker(plugin):
  flicker = {p: (r["count_changes"], r["appearances"]) for p, r in plugin["pairs"].items()
             if r["count_changes"] or r["appearances"]}
  assert not flicker, f"(count changes, appearances) per pair: {flicker}"


@pytest.mark.parametrize("body", PLANE_BODIES + MESH_BODIES)
def test_resting_drift(resting, body):
  _drift(resting, body)


@pytest.mark.parametrize(
  "pair",
  [f"floor-{b}" for b in PLANE_BODIES + MESH_BODIES[:1]] + ["meshcube0-meshcube1"],
)
def test_resting_contact_motion(resting, pair):
  _motion(resting, pair)


def test_resting_contacts_persist(resting):
  """After settling no resting pair loses, regains or changes its number of contacts."""
  plugin, _ = resting
  assert len(plugin["pairs"]) == 5, sorted(plugin["pairs"])
  _no_flicker(plugin)


@pytest.mark.parametrize("body", PLANE_BODIES + MESH_BODIES)
def test_resting_height_matches_mujoco(resting, body):
  """The rest height (penetration under load) agrees with MuJoCo C's to the drift tolerance.

  Analytic pairs agree to 1e-7 m. The upper mesh cube rests 2e-5 m higher than under MuJoCo C
  (its 4 contacts sit at the patch's corners).
  """
  plugin, ref = resting
  got, want = plugin["bodies"][body]["final_z"], ref["bodies"][body]["final_z"]
  assert abs(got - want) < stability.MAX_DRIFT, f"{body}: rests at z={got:.6f}, MuJoCo C {want:.6f}"


def test_stack_stands(stack):
  """After 2000 steps every box is within 1 cm of where it started and tilted < 2 degrees."""
  plugin, ref = stack
  got = plugin["stack"]
  assert got["standing"], f"stack: {got} (MuJoCo C {ref['stack']})"


@pytest.mark.parametrize("body", stability.STACK)
def test_stack_drift(stack, body):
  _drift(stack, body)


def test_stack_contacts_still(stack):
  """Every stack pair's contacts move < 1 mm per step and none comes or goes after settling."""
  plugin, _ = stack
  for pair in plugin["pairs"]:
    _motion(stack, pair)
  _no_flicker(plugin)
