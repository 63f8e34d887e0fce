"""Make the library's household meshes and articulated fixtures (run once; outputs are committed).

Every object is built here from geometric primitives with trimesh: nothing is
downloaded or copied. Sizes are in metres for a robot whose task cube has a
half-size of 0.02 m (Panda, UR5e); task files scale them for smaller arms.
Each mesh stands on z = 0 with its axis on z, so a task places it by its base.

    python scenes/assets/make_meshes.py            # writes scenes/assets/meshes/*.obj, *.xml
    python scenes/assets/make_meshes.py --collision  # and pre-computes their convex parts

`--collision` runs `scenes.assembly.mesh_collision.convex_parts` on each mesh and writes
the parts next to it, so no user waits for the decomposition of a library mesh.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Callable
from pathlib import Path

import numpy as np
import trimesh
from trimesh.creation import box, revolve, torus

OUT = Path(__file__).resolve().parent / "meshes"
SECTIONS = 32  # facets around a revolved object: a few hundred to a few thousand faces each


def _revolve(profile: list[tuple[float, float]]) -> trimesh.Trimesh:
    """A closed solid of revolution about z from a (radius, z) profile that starts and ends on the axis."""
    return revolve(np.asarray(profile, dtype=float), sections=SECTIONS)


def _shell(outer: list[tuple[float, float]], wall: float, bottom: float) -> trimesh.Trimesh:
    """An open-topped vessel: the outer (radius, z) profile from the base to the rim, walls `wall` thick."""
    inner = [(max(r - wall, 0.0), max(z, bottom)) for r, z in reversed(outer)]
    return _revolve([(0.0, 0.0), *outer, *inner, (0.0, bottom)])


def mug() -> trimesh.Trimesh:
    """A straight mug, 7 cm across and 8 cm tall, with a ring handle on +x."""
    r, h = 0.035, 0.08
    body = _shell([(r, 0.0), (r, h)], wall=0.005, bottom=0.008)
    ring = torus(0.022, 0.0055, major_sections=24, minor_sections=10)
    ring.apply_transform(trimesh.transformations.rotation_matrix(np.pi / 2, [1, 0, 0]))
    ring.apply_translation([r + 0.006, 0.0, 0.045])
    keep = ring.vertices[ring.faces].mean(axis=1)[:, 0] > r - 0.003  # the half of the ring outside the wall
    ring.update_faces(keep)
    ring.remove_unreferenced_vertices()
    return trimesh.util.concatenate([body, ring])


def bowl() -> trimesh.Trimesh:
    """A round bowl, 13 cm across and 5 cm tall."""
    angles = np.linspace(0.0, np.pi / 2, 9)
    outer = [(0.03 + 0.035 * np.sin(a), 0.05 * (1 - np.cos(a))) for a in angles]
    return _shell([(0.03, 0.0), *outer[1:]], wall=0.005, bottom=0.006)


def bottle() -> trimesh.Trimesh:
    """A closed bottle, 5.6 cm across and 17 cm tall, with a 2.4 cm neck to hold it by."""
    return _revolve([(0.0, 0.0), (0.028, 0.0), (0.028, 0.11), (0.02, 0.128), (0.012, 0.14), (0.012, 0.165),
                     (0.013, 0.166), (0.013, 0.17), (0.0, 0.17)])


def can() -> trimesh.Trimesh:
    """A drink can, 5.4 cm across and 9 cm tall, with bevelled rims."""
    return _revolve([(0.0, 0.0), (0.022, 0.0), (0.027, 0.006), (0.027, 0.082), (0.023, 0.09), (0.0, 0.09)])


def plate() -> trimesh.Trimesh:
    """A dinner plate, 16 cm across, a 1.8 cm rim around a flat well."""
    return _revolve([(0.0, 0.0), (0.05, 0.0), (0.08, 0.016), (0.08, 0.018), (0.074, 0.018), (0.05, 0.005), (0.0, 0.005)])


def cup() -> trimesh.Trimesh:
    """A tapered drinking glass, 6.4 cm across at the rim, 9 cm tall."""
    return _shell([(0.025, 0.0), (0.032, 0.09)], wall=0.004, bottom=0.008)


def basket() -> trimesh.Trimesh:
    """A square basket, 16 cm inside, 6 cm tall walls, for putting things in."""
    half, wall, h = 0.08, 0.006, 0.06
    parts = [box([2 * (half + wall), 2 * (half + wall), wall], trimesh.transformations.translation_matrix([0, 0, wall / 2]))]
    for sx, sy in ((1, 0), (-1, 0), (0, 1), (0, -1)):
        ext = [wall, 2 * (half + wall), h] if sx else [2 * (half + wall), wall, h]
        parts.append(box(ext, trimesh.transformations.translation_matrix([sx * (half + wall / 2), sy * (half + wall / 2), h / 2])))
    return trimesh.util.concatenate(parts)


def square_hole() -> trimesh.Trimesh:
    """A block with a square through-hole 3.2 cm wide (for a 2.4 cm square peg), 4 cm tall."""
    inner, wall, h = 0.016, 0.02, 0.04
    parts = []
    for sx, sy in ((1, 0), (-1, 0), (0, 1), (0, -1)):
        ext = [wall, 2 * (inner + wall), h] if sx else [2 * inner, wall, h]
        off = inner + wall / 2
        parts.append(box(ext, trimesh.transformations.translation_matrix([sx * off, sy * off, h / 2])))
    return trimesh.util.concatenate(parts)


def round_hole() -> trimesh.Trimesh:
    """A thick ring with a round through-hole 3.2 cm across (for a 2.4 cm round peg), 4 cm tall."""
    return _revolve([(0.016, 0.0), (0.036, 0.0), (0.036, 0.04), (0.016, 0.04), (0.016, 0.0)])


MESHES: dict[str, Callable[[], trimesh.Trimesh]] = {
    "mug": mug, "bowl": bowl, "bottle": bottle, "can": can, "plate": plate, "cup": cup,
    "basket": basket, "square_hole": square_hole, "round_hole": round_hole,
}

DRAWER_XML = """<mujoco model="drawer_cabinet">
  <compiler angle="radian"/>
  <!-- A cabinet with one drawer that slides out toward -x (the robot); written by make_meshes.py.
       Frame: origin on the table under the cabinet's centre; the drawer joint is 0 when shut.
       Names: the drawer body `drawer`, its joint `drawer_slide` (0 to 0.12 m), its handle geom
       `drawer_handle` and site `drawer_handle_site`, the inside of the drawer `drawer_inside` (a site). -->
  <default>
    <default class="cabinet">
      <geom type="box" rgba="0.55 0.42 0.3 1" friction="1 0.005 0.0001"/>
    </default>
  </default>
  <worldbody>
    <body name="cabinet" pos="0 0 0">
      <geom class="cabinet" name="cabinet_bottom" size="0.1 0.13 0.005" pos="0 0 0.005"/>
      <geom class="cabinet" name="cabinet_top" size="0.1 0.13 0.005" pos="0 0 0.125"/>
      <geom class="cabinet" name="cabinet_left" size="0.1 0.005 0.06" pos="0 -0.125 0.065"/>
      <geom class="cabinet" name="cabinet_right" size="0.1 0.005 0.06" pos="0 0.125 0.065"/>
      <geom class="cabinet" name="cabinet_back" size="0.005 0.13 0.06" pos="0.095 0 0.065"/>
      <body name="drawer" pos="0 0 0.012">
        <joint name="drawer_slide" type="slide" axis="-1 0 0" range="0 0.12" damping="8" frictionloss="0.3" armature="0.05"/>
        <geom class="cabinet" name="drawer_floor" size="0.09 0.115 0.004" pos="0 0 0.004" rgba="0.75 0.62 0.45 1" density="300"/>
        <geom class="cabinet" name="drawer_front" size="0.006 0.12 0.05" pos="-0.096 0 0.05" rgba="0.75 0.62 0.45 1" density="300"/>
        <geom class="cabinet" name="drawer_back" size="0.004 0.115 0.035" pos="0.086 0 0.035" rgba="0.75 0.62 0.45 1" density="300"/>
        <geom class="cabinet" name="drawer_left" size="0.09 0.004 0.035" pos="0 -0.111 0.035" rgba="0.75 0.62 0.45 1" density="300"/>
        <geom class="cabinet" name="drawer_right" size="0.09 0.004 0.035" pos="0 0.111 0.035" rgba="0.75 0.62 0.45 1" density="300"/>
        <geom name="drawer_handle" type="capsule" fromto="-0.13 -0.04 0.055 -0.13 0.04 0.055" size="0.007" rgba="0.8 0.8 0.82 1"
              friction="1.2 0.01 0.0005" condim="4" density="800"/>
        <geom type="box" size="0.014 0.005 0.005" pos="-0.115 -0.035 0.055" rgba="0.8 0.8 0.82 1"/>
        <geom type="box" size="0.014 0.005 0.005" pos="-0.115 0.035 0.055" rgba="0.8 0.8 0.82 1"/>
        <site name="drawer_handle_site" pos="-0.13 0 0.055" size="0.005"/>
        <site name="drawer_inside" type="box" pos="0 0 0.04" size="0.082 0.107 0.035" rgba="0 0 0 0"/>
      </body>
    </body>
  </worldbody>
</mujoco>
"""

CABINET_DOOR_XML = """<mujoco model="cabinet_door">
  <compiler angle="radian"/>
  <!-- A low cupboard whose door swings open toward -x (the robot) on a hinge at +y; written by
       make_meshes.py. Frame: origin on the table under the cupboard's centre; the hinge is 0 when
       shut. Names: joint `cupboard_hinge` (0 to 1.9 rad), handle geom `cupboard_handle`, site
       `cupboard_handle_site`. -->
  <default>
    <default class="cupboard">
      <geom type="box" rgba="0.35 0.45 0.55 1" friction="1 0.005 0.0001"/>
    </default>
  </default>
  <worldbody>
    <body name="cupboard" pos="0 0 0">
      <geom class="cupboard" size="0.08 0.12 0.005" pos="0 0 0.005"/>
      <geom class="cupboard" size="0.08 0.12 0.005" pos="0 0 0.175"/>
      <geom class="cupboard" size="0.08 0.005 0.08" pos="0 -0.115 0.09"/>
      <geom class="cupboard" size="0.08 0.005 0.08" pos="0 0.115 0.09"/>
      <geom class="cupboard" size="0.005 0.12 0.08" pos="0.075 0 0.09"/>
      <body name="cupboard_door" pos="-0.086 0.12 0">
        <joint name="cupboard_hinge" type="hinge" axis="0 0 -1" range="0 1.9" damping="0.5" frictionloss="0.05" armature="0.01"/>
        <geom class="cupboard" name="cupboard_panel" size="0.006 0.12 0.085" pos="0 -0.12 0.09" rgba="0.5 0.6 0.7 1" density="300"/>
        <geom name="cupboard_handle" type="capsule" fromto="-0.035 -0.2 0.06 -0.035 -0.2 0.12" size="0.007" rgba="0.8 0.8 0.82 1"
              friction="1.2 0.01 0.0005" condim="4" density="800"/>
        <geom type="box" size="0.014 0.005 0.005" pos="-0.02 -0.2 0.065" rgba="0.8 0.8 0.82 1"/>
        <geom type="box" size="0.014 0.005 0.005" pos="-0.02 -0.2 0.115" rgba="0.8 0.8 0.82 1"/>
        <site name="cupboard_handle_site" pos="-0.035 -0.2 0.09" size="0.005"/>
      </body>
    </body>
  </worldbody>
</mujoco>
"""

L_BLOCK_XML = """<mujoco model="l_block">
  <compiler angle="radian"/>
  <!-- An L-shaped block of two boxes, free to move: an object whose yaw matters (it has one way to be
       held across its long arm, two with the gripper turned half a turn); written by make_meshes.py.
       Frame: origin on the table under the middle of the long arm, the long arm along x, the short arm
       at its +x end reaching toward +y. A parallel gripper holds the long arm across (fingers along y)
       above the origin. Names: body `l_block`, its joint `l_block_joint`. -->
  <default>
    <default class="l_block">
      <geom type="box" rgba="0.9 0.55 0.15 1" friction="1 0.005 0.0001" condim="4" density="400"/>
    </default>
  </default>
  <worldbody>
    <body name="l_block" pos="0 0 0">
      <freejoint name="l_block_joint"/>
      <geom class="l_block" name="l_block_long" size="0.05 0.015 0.02" pos="0 0 0.02"/>
      <geom class="l_block" name="l_block_short" size="0.015 0.035 0.02" pos="0.035 0.05 0.02"/>
    </body>
  </worldbody>
</mujoco>
"""

MJCF: dict[str, str] = {"drawer_cabinet": DRAWER_XML, "cabinet_door": CABINET_DOOR_XML, "l_block": L_BLOCK_XML}


def _obj_text(mesh: trimesh.Trimesh, name: str) -> str:
    """A small, stable OBJ (6 decimals, no tool header) so regenerating gives the same bytes and hash."""
    lines = [f"# {name}: made by scenes/assets/make_meshes.py", f"o {name}"]
    lines += [f"v {x:.6f} {y:.6f} {z:.6f}" for x, y, z in np.asarray(mesh.vertices)]
    lines += [f"f {a + 1} {b + 1} {c + 1}" for a, b, c in np.asarray(mesh.faces)]
    return "\n".join(lines) + "\n"


def write_all(out: Path = OUT, collision: bool = False) -> list[Path]:
    """Write every mesh (OBJ) and fixture (MJCF) into `out`; with `collision`, also their convex parts."""
    out.mkdir(parents=True, exist_ok=True)
    written = []
    for name, make in MESHES.items():
        mesh = make()
        mesh.merge_vertices()
        path = out / f"{name}.obj"
        path.write_text(_obj_text(mesh, name))
        written.append(path)
    for name, xml in MJCF.items():
        path = out / f"{name}.xml"
        path.write_text(xml)
        written.append(path)
    if collision:
        sys.path.insert(0, str(Path(__file__).resolve().parents[2]))
        from scenes.assembly.mesh_collision import ship_parts

        for name in MESHES:
            written.append(ship_parts(out / f"{name}.obj"))
    return written


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=OUT)
    parser.add_argument("--collision", action="store_true", help="also pre-compute each mesh's convex parts (coacd)")
    args = parser.parse_args()
    for path in write_all(args.out, args.collision):
        print(path)


if __name__ == "__main__":
    main()
