"""Pair classes routed to MuJoCo Warp's own narrow phase (Options.stock_pair_classes): the routed
pairs get stock's contacts bit for bit, the others the plugin's, and a model whose every pair is
routed collides through MuJoCo Warp's own stage."""

import collections

import mujoco_warp as mjw
import numpy as np
import pytest
from mujoco_warp._src.types import GeomType

import mjx_supportfield as sf
from conftest import load
from conftest import sorted_rows
from mjx_supportfield.options import PAIR_CLASSES
from mjx_supportfield.stages.routing import PairClass

_CUBE = " ".join(f"{x} {y} {z}" for x in (-.1, .1) for y in (-.1, .1) for z in (-.1, .1))
_ELEVATION = " ".join(f"{0.5 + 0.3 * np.sin(i) * np.cos(j):.3f}" for i in range(8) for j in range(8))


def _stack(x: float, below: str, above: str) -> str:
  """Two free bodies at ``x``, the upper sunk 1 cm into the lower (both sunk into the floor)."""
  return (f"<body pos='{x} 0 .095'><freejoint/><geom {below}/></body>"
          f"<body pos='{x} 0 .285'><freejoint/><geom {above}/></body>")


# a pair or two of each class, apart from one another
_MODEL = f"""<mujoco>
  <asset><mesh name="cube" vertex="{_CUBE}"/>
    <hfield name="bumps" nrow="8" ncol="8" size=".5 .5 .1 .05" elevation="{_ELEVATION}"/></asset>
  <worldbody><geom name="floor" type="plane" size="0 0 .1"/>
    {_stack(0, "type='box' size='.1 .1 .1'", "type='capsule' size='.1 .1' euler='0 90 0'")}
    {_stack(1, "type='cylinder' size='.1 .1'", "type='ellipsoid' size='.1 .12 .1'")}
    {_stack(2, "type='box' size='.1 .1 .1'", "type='cylinder' size='.1 .1' euler='20 0 0'")}
    {_stack(3, "name='m1' type='mesh' mesh='cube'", "type='box' size='.1 .1 .1' euler='0 0 30'")}
    {_stack(4, "type='mesh' mesh='cube'", "type='mesh' mesh='cube' euler='0 0 45'")}
    <geom type="hfield" hfield="bumps" pos="6 0 0"/>
    <body pos="6 0 .16"><freejoint/><geom type="sphere" size=".1"/></body>
    <body pos="6.3 .2 .16"><freejoint/><geom type="box" size=".08 .08 .08"/></body>
  </worldbody></mujoco>"""
_NWORLD = 2


def _by_class(sim) -> dict:
  """Each world's contacts grouped by the class of their geom pair: class -> contact fields."""
  gtype = np.asarray(sim.mjm.geom_type)
  n = min(int(sim.d.nacon.numpy()[0]), sim.d.naconmax)
  c = sim.d.contact
  fields = {"dist": c.dist.numpy()[:n], "pos": c.pos.numpy()[:n], "frame": c.frame.numpy()[:n],
            "geom": c.geom.numpy()[:n], "worldid": c.worldid.numpy()[:n], "friction": c.friction.numpy()[:n]}
  rows = collections.defaultdict(list)
  for i in range(n):
    t1, t2 = sorted(int(gtype[g]) for g in fields["geom"][i])
    rows[PairClass.of(GeomType(t1), GeomType(t2)).name.lower()].append(i)
  return {name: sorted_rows({k: v[idx] for k, v in fields.items()}) for name, idx in rows.items()}


def _collide(options=None, plugin=True):
  sim = load(_MODEL, nworld=_NWORLD, naconmax=512)
  collider = sf.install(sim.mjm, sim.m, options or sf.Options()) if plugin else None
  mjw.collision(sim.m, sim.d)
  return _by_class(sim), collider, sim


def _assert_same(a: dict, b: dict):
  assert a.keys() == b.keys()
  for k in a:
    np.testing.assert_array_equal(a[k], b[k], err_msg=k)


@pytest.mark.parametrize("routed", PAIR_CLASSES)
def test_routed_class_gets_stock_contacts_the_rest_the_plugins(routed):
  stock, _, _ = _collide(plugin=False)
  plugin, _, _ = _collide(sf.Options(stock_pair_classes=()))
  mixed, collider, sim = _collide(sf.Options(stock_pair_classes=(routed,)))
  assert set(stock) == set(PAIR_CLASSES), "every class in the model touches"
  assert not collider.stock_path
  for name in PAIR_CLASSES:
    _assert_same(mixed[name], stock[name] if name == routed else plugin[name])
  # the routed pairs were listed for MuJoCo Warp: its pair counter holds them
  touching = {(int(w), *map(int, g)) for w, g in zip(stock[routed]["worldid"], stock[routed]["geom"])}
  assert int(sim.d.ncollision.numpy()[0]) >= len(touching)


def test_every_class_routed_collides_through_stock():
  stock, _, _ = _collide(plugin=False)
  routed, collider, sim = _collide(sf.Options(stock_pair_classes=PAIR_CLASSES))
  assert collider.stock_path
  assert collider.stats(sim.d)["path"] == "stock"
  for name in PAIR_CLASSES:
    _assert_same(routed[name], stock[name])


def test_nonconvex_mesh_stays_the_plugins():
  """A non-convex mesh's pairs are the plugin's whatever their class: MuJoCo Warp has only its hull."""
  options = {"nonconvex_geoms": ("m1",)}
  own, _, sim = _collide(sf.Options(stock_pair_classes=(), **options))
  routed, collider, _ = _collide(sf.Options(stock_pair_classes=("mesh", "analytic"), **options))
  m1 = sim.mjm.geom("m1").id
  for name in ("mesh", "analytic"):  # the mesh on the box, the floor under the mesh
    of_m1 = (own[name]["geom"] == m1).any(axis=1)
    assert of_m1.any()
    np.testing.assert_array_equal(routed[name]["dist"][(routed[name]["geom"] == m1).any(axis=1)],
                                  own[name]["dist"][of_m1])


def test_unknown_pair_class_is_refused():
  with pytest.raises(ValueError, match="stock_pair_classes.*'meshes'.*analytic, primitive"):
    sf.Options(stock_pair_classes=("meshes",))
  with pytest.raises(ValueError, match="stock_pair_classes: expected a list"):
    sf.Options(stock_pair_classes="mesh")


def test_pair_class_names_match_the_options():
  assert tuple(c.name.lower() for c in PairClass) == PAIR_CLASSES
