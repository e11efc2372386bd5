#!/usr/bin/env python3
"""Sanity checks for the MJCF scenes in models/ (MuJoCo C, CPU only).

Run from the repo root (works from any cwd):

    python models/check_models.py [--steps 300] [scene.xml ...]

For each scene: load with mujoco.MjModel.from_xml_path, mj_forward, then step.
Fails (exit code 1) if
  * a geom has no name,
  * there are no contacts at t=0 (except scenes whose bodies are all dropped),
  * any state becomes non-finite or MuJoCo raises a warning,
  * a body's COM goes below the floor (z < 0), a floor contact is ever deeper
    than MAX_FLOOR_PENETRATION (soft contacts let dropped bodies sink ~1 cm on
    impact with default solref) or deeper than MAX_FINAL_PENETRATION at the end,
  * there are no contacts at the end (everything should be resting),
  * a body exceeds MAX_LIN_SPEED / MAX_ANG_SPEED (explosion),
  * convex_pile has no mesh-mesh contact within the simulated steps.
"""

from __future__ import annotations

import argparse
import os
import sys

import mujoco
import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
SCENES = [
    "primitives_plane.xml",
    "convex_pile.xml",
    "box_stack.xml",
    "mesh_on_plane.xml",
    "resting.xml",
    "terrain.xml",
    "nonconvex.xml",
]
# scenes whose bodies are all dropped (no contact at t=0 is expected)
DROPPED = {"terrain.xml"}
MAX_FLOOR_PENETRATION = 0.025  # m, at any step (impacts)
MAX_FINAL_PENETRATION = 0.005  # m, after the last step (settled)
MAX_LIN_SPEED = 5.0  # m/s   (a drop from 0.3 m reaches ~2.4 m/s)
MAX_ANG_SPEED = 200.0  # rad/s
# scene -> requirement on geom-type pairs seen at some step (1..nsteps)
REQUIRE_PAIR = {"convex_pile.xml": ("mesh", "mesh")}

TYPE_NAMES = {int(v): k[len("mjGEOM_"):].lower()
              for k, v in mujoco.mjtGeom.__members__.items() if k.startswith("mjGEOM_")}
WARNING_NAMES = {int(v): k for k, v in mujoco.mjtWarning.__members__.items()
                 if k.startswith("mjWARN_")}


def pair_kind(m: mujoco.MjModel, c) -> tuple[str, str]:
    return tuple(sorted(TYPE_NAMES[int(m.geom_type[g])] for g in c.geom))


def check_scene(fname: str, nsteps: int) -> tuple[bool, dict]:
    path = os.path.join(HERE, fname)
    m = mujoco.MjModel.from_xml_path(path)
    d = mujoco.MjData(m)
    errors: list[str] = []

    geom_names = [mujoco.mj_id2name(m, mujoco.mjtObj.mjOBJ_GEOM, i) for i in range(m.ngeom)]
    if any(not n for n in geom_names):
        errors.append(f"unnamed geoms: {[i for i, n in enumerate(geom_names) if not n]}")
    floor = [i for i in range(m.ngeom) if m.geom_type[i] == mujoco.mjtGeom.mjGEOM_PLANE]
    free_bodies = [b for b in range(1, m.nbody)]

    mujoco.mj_forward(m, d)
    ncon0 = d.ncon
    kinds0 = sorted({pair_kind(m, c) for c in d.contact[: d.ncon]})
    if ncon0 == 0 and os.path.basename(path) not in DROPPED:
        errors.append("no contacts at t=0")

    seen_kinds: set[tuple[str, str]] = set()
    max_lin = max_ang = 0.0
    min_com_z = np.inf
    min_floor_dist = np.inf
    for step in range(1, nsteps + 1):
        mujoco.mj_step(m, d)
        if not (np.all(np.isfinite(d.qpos)) and np.all(np.isfinite(d.qvel))):
            errors.append(f"non-finite state at step {step}")
            break
        for c in d.contact[: d.ncon]:
            seen_kinds.add(pair_kind(m, c))
            if c.geom[0] in floor or c.geom[1] in floor:
                min_floor_dist = min(min_floor_dist, float(c.dist))
        # free joints: qvel = [lin(3), ang(3)] per body
        v = d.qvel.reshape(-1, 6)
        max_lin = max(max_lin, float(np.linalg.norm(v[:, :3], axis=1).max()))
        max_ang = max(max_ang, float(np.linalg.norm(v[:, 3:], axis=1).max()))
        min_com_z = min(min_com_z, float(d.xipos[free_bodies, 2].min()))

    final_floor_dist = min((float(c.dist) for c in d.contact[: d.ncon]
                            if c.geom[0] in floor or c.geom[1] in floor), default=0.0)
    if d.ncon == 0:
        errors.append(f"no contacts after {nsteps} steps")
    if final_floor_dist < -MAX_FINAL_PENETRATION:
        errors.append(f"final floor penetration {-final_floor_dist:.4f} m > "
                      f"{MAX_FINAL_PENETRATION}")
    nwarn = {WARNING_NAMES.get(i, str(i)): int(d.warning[i].number)
             for i in range(len(d.warning)) if d.warning[i].number}
    if nwarn:
        errors.append(f"mujoco warnings: {nwarn}")
    if min_com_z < 0:
        errors.append(f"a body COM went below the floor (min z {min_com_z:.4f})")
    if min_floor_dist < -MAX_FLOOR_PENETRATION:
        errors.append(f"floor penetration {-min_floor_dist:.4f} m > {MAX_FLOOR_PENETRATION}")
    if max_lin > MAX_LIN_SPEED or max_ang > MAX_ANG_SPEED:
        errors.append(f"velocity blow-up: lin {max_lin:.2f} m/s, ang {max_ang:.1f} rad/s")
    req = REQUIRE_PAIR.get(fname)
    if req and tuple(sorted(req)) not in seen_kinds:
        errors.append(f"no {req[0]}-{req[1]} contact within {nsteps} steps")

    info = dict(
        ngeom=m.ngeom, nbody=m.nbody - 1, nmesh=m.nmesh,
        nmeshvert=int(m.mesh_vertnum.sum()) if m.nmesh else 0,
        ncon0=ncon0, ncon_end=d.ncon, kinds0=kinds0,
        kinds_all=sorted(seen_kinds), max_lin=max_lin, max_ang=max_ang,
        min_com_z=min_com_z, min_floor_dist=min_floor_dist,
        final_floor_dist=final_floor_dist, time=d.time,
    )
    ok = not errors
    print(f"[{'OK' if ok else 'FAIL'}] {fname}: {info['ngeom']} geoms "
          f"({info['nbody']} free bodies, {info['nmesh']} meshes, "
          f"{info['nmeshvert']} mesh verts)")
    print(f"    ncon t=0: {ncon0}   ncon after {nsteps} steps (t={d.time:.3f}): {d.ncon}")
    print(f"    pair kinds t=0: {', '.join('-'.join(k) for k in kinds0)}")
    print(f"    pair kinds seen while stepping: {', '.join('-'.join(k) for k in sorted(seen_kinds))}")
    print(f"    max |v| {max_lin:.3f} m/s, max |w| {max_ang:.2f} rad/s, "
          f"min COM z {min_com_z:.4f} m")
    print(f"    deepest floor contact dist: {min_floor_dist:.4f} m (any step), "
          f"{final_floor_dist:.4f} m (end)")
    for e in errors:
        print(f"    ERROR: {e}")
    return ok, info


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("scenes", nargs="*", default=SCENES)
    ap.add_argument("--steps", type=int, default=300)
    args = ap.parse_args()
    all_ok = True
    for s in args.scenes:
        ok, _ = check_scene(os.path.basename(s), args.steps)
        all_ok &= ok
    print("all scenes OK" if all_ok else "SOME SCENES FAILED")
    return 0 if all_ok else 1


if __name__ == "__main__":
    sys.exit(main())
