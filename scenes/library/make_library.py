"""Write the task library from a few templates (LIBERO-style): one TOML task file and its scripts per task.

    python scenes/library/make_library.py     # writes scenes/library/*.toml and scenes/scripts/<task>*.json

Each family below is a template over objects; the generated files are committed,
and this script is the record of how they were made. Lengths are metres for a
robot whose task cube has a 0.02 m half-size (Panda, UR5e); a task file's sizes
and positions are relative to the robot's layout (`scale = "robot"`), so an
SO-101 gets the same scene at 0.75 size. Scripts cannot scale themselves, so a
task that fits the SO-101 also gets `<task>.so101.json` at that size.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from pathlib import Path

HERE = Path(__file__).resolve().parent
SCRIPTS = HERE.parent / "scripts"
MESHES = "../assets/meshes"  # relative to a task file
SO101_SCALE = 0.75  # SO-101's cube half-size over Panda's (0.015 / 0.02)
ARMS = ("panda", "ur5e", "so101")
BIG_ARMS = ("panda", "ur5e")

RED, BLUE, GREEN, YELLOW = [0.85, 0.2, 0.15, 1.0], [0.15, 0.45, 0.85, 1.0], [0.2, 0.7, 0.3, 1.0], [0.9, 0.75, 0.2, 1.0]
WHITE, STEEL, WOOD = [0.92, 0.92, 0.9, 1.0], [0.7, 0.72, 0.75, 1.0], [0.6, 0.45, 0.3, 1.0]


@dataclass(frozen=True)
class Thing:
    """A task object: how it is made, how tall, where a gripper holds it and where things rest on or in it.

    grasp: EE offset (m) from the centre of its bottom that holds it; top: height (m);
    floor: height (m) of the surface inside or on it; fits: robots that can hold it.
    """

    name: str
    fields: dict
    top: float
    grasp: tuple[float, float, float] = (0.0, 0.0, 0.0)
    floor: float = 0.0
    fits: tuple[str, ...] = ARMS
    base: float = 0.0  # body origin above the table (m): 0 for meshes, half the height for primitives


def mesh(name: str, rgba, top: float, grasp=(0.0, 0.0, 0.0), floor: float = 0.0, fits=ARMS, **extra) -> Thing:
    return Thing(name, {"mesh": f"{MESHES}/{name}.obj", "scale": 1.0, "rgba": rgba, **extra}, top, grasp, floor, fits)


def cube(name: str, rgba, half: float = 0.02) -> Thing:
    return Thing(name, {"box": [half, half, half], "rgba": rgba}, 2 * half, grasp=(0.0, 0.0, half), floor=2 * half, base=half)


MUG = mesh("mug", [0.25, 0.45, 0.75, 1.0], 0.08, grasp=(0.0, 0.0, 0.05), floor=0.008)  # the whole body: an open Panda hand spans the rim
MUG_BY_RIM = mesh("mug", [0.25, 0.45, 0.75, 1.0], 0.08, grasp=(0.0, -0.031, 0.065), floor=0.008)  # the SO-101's jaw takes the wall
CUP = mesh("cup", [0.75, 0.85, 0.9, 1.0], 0.09, grasp=(0.0, -0.029, 0.072), floor=0.008)
BOWL = mesh("bowl", [0.9, 0.85, 0.75, 1.0], 0.05, grasp=(0.0, -0.0625, 0.042), floor=0.006)
BOTTLE = mesh("bottle", [0.25, 0.6, 0.35, 1.0], 0.17, grasp=(0.0, 0.0, 0.15), floor=0.17)
CAN = mesh("can", [0.8, 0.15, 0.15, 1.0], 0.09, grasp=(0.0, 0.0, 0.05), floor=0.09, fits=BIG_ARMS)
PLATE = mesh("plate", WHITE, 0.018, floor=0.005)
BASKET = mesh("basket", WOOD, 0.06, floor=0.006)
CUBE = cube("cube", RED)
# Two boxes in an L (scenes/assets/meshes/l_block.xml; its origin on the table under the long arm's middle):
# one way round, so a script turns the hand to its yaw (`"align": "yaw"`) to hold the long arm across.
L_BLOCK = Thing("l_block", {"mjcf": f"{MESHES}/l_block.xml", "yaw": [-3.1416, 3.1416]}, 0.04, grasp=(0.0, 0.0, 0.02),
                fits=BIG_ARMS)


@dataclass
class Task:
    name: str
    family: str
    instruction: str
    instructions: list[str]
    objects: list[dict]
    success: str
    subtasks: list[dict]
    steps: list[dict]  # the script at Panda size; lengths scale for the SO-101
    robots: tuple[str, ...] = ARMS
    hold: float = 0.3
    extra: dict = field(default_factory=dict)


TALL = 0.1  # m: an object this tall starts clear of the workspace centre, where the SO-101's hand rests 10 cm up at Panda size
CLEAR_Y = 0.075  # m: the least |y| such an object starts at


def obj(thing: Thing, name: str | None = None, x=(-0.1, -0.04), y=(0.04, 0.1), **over) -> dict:
    """An object entry placed in a table region (m from the workspace centre)."""
    if thing.top > TALL:
        y = (max(y[0], CLEAR_Y), max(y[1], CLEAR_Y + 0.03))
    entry = {"name": name or thing.name, **thing.fields, "region": {"x": list(x), "y": list(y)}}
    if "yaw" in entry:
        entry["region"]["yaw"] = entry.pop("yaw")
    entry.update(over)
    return entry


def add(a, b) -> list[float]:
    return [round(u + v, 4) for u, v in zip(a, b)]


def pick_steps(thing: Thing, name: str, lift: float) -> list[dict]:
    """Reach above the object, close on it at its grasp offset, lift by `lift` (m)."""
    g = add(thing.grasp, (0.0, 0.0, -thing.base))
    return [
        {"duration": 1.5, "to_body": name, "offset": add(g, (0, 0, 0.08)), "gripper": "open"},
        {"duration": 1.0, "to_body": name, "offset": g},
        {"duration": 0.6, "gripper": "close"},
        {"duration": 1.0, "move": [0, 0, lift]},
    ]


def place_steps(thing: Thing, target: Thing, target_name: str, carry: float, release: float = 0.012) -> list[dict]:
    """Carry the held object over `target` and let it go `release` (m) above the surface in or on it."""
    g = list(thing.grasp)  # the EE stays this far above the held object's bottom
    rest = target.floor - target.base
    return [
        {"duration": 1.5, "to_body": target_name, "offset": add(g, (0, 0, rest + carry))},
        {"duration": 0.8, "to_body": target_name, "offset": add(g, (0, 0, rest + release))},
        {"duration": 0.6, "gripper": "open"},
        {"duration": 0.8, "move": [0, 0, 0.1]},
    ]


def the(name: str) -> str:
    return name.replace("_", " ")


# --- families -----------------------------------------------------------------------------------------

def pick_place(thing: Thing, target: Thing, word: str, x=(-0.1, -0.04), y=(0.04, 0.1)) -> Task:
    """put {object} in/on {container}; x, y: the object's region (m), kept clear of the container's on every seed"""
    carry = target.top - target.floor + 0.05
    steps = pick_steps(thing, thing.name, target.top + 0.05) + place_steps(thing, target, target.name, carry) + [{"duration": 0.5}]
    pred = "inside" if word == "in" else "on"
    return Task(
        f"put_{thing.name}_{word}_{target.name}", "pick_place", f"Put the {the(thing.name)} {word} the {the(target.name)}.",
        [f"Place the {the(thing.name)} {'into' if word == 'in' else 'onto'} the {the(target.name)}.",
         f"Pick up the {the(thing.name)} and put it {word} the {the(target.name)}."],
        [obj(thing, x=x, y=y), obj(target, x=(0.02, 0.08), y=(-0.1, -0.06))],
        f"{pred}({thing.name}, {target.name}) and at_rest({thing.name})",
        [{"object": thing.name, "kind": "grasp"}, {"object": target.name, "kind": "place"}], steps,
        robots=tuple(r for r in ARMS if r in thing.fits and r in target.fits),
    )


def lift(thing: Thing) -> Task:
    """pick up {object}"""
    return Task(
        f"lift_{thing.name}", "lift", f"Pick up the {the(thing.name)}.",
        [f"Lift the {the(thing.name)} off the table.", f"Grab the {the(thing.name)} and raise it."],
        [obj(thing, x=(-0.06, 0.06), y=(-0.06, 0.06))], f"grasped({thing.name}) and lifted({thing.name}, 0.05)",
        [{"object": thing.name, "kind": "grasp"}], pick_steps(thing, thing.name, 0.15) + [{"duration": 0.5}], robots=thing.fits,
    )


def lift_at_any_yaw(thing: Thing, words: str) -> Task:
    """pick up {object} placed at any yaw: the hand turns to the object's yaw (mod pi) as it comes down"""
    steps = pick_steps(thing, thing.name, 0.15) + [{"duration": 0.5}]
    for step in steps[:2]:  # the reach and the descent: turned to the object, the nearer of the two grasps
        step["align"] = "yaw"
    return Task(
        f"lift_{thing.name}", "lift", f"Pick up the {words}.",
        [f"Lift the {words} off the table, however it lies.", f"Grab the long arm of the {words} and raise it."],
        [obj(thing, x=(-0.06, 0.06), y=(-0.06, 0.06))], f"grasped({thing.name}) and lifted({thing.name}, 0.05)",
        [{"object": thing.name, "kind": "grasp"}], steps, robots=thing.fits,
    )


def stack_three() -> Task:
    red, blue, green = cube("red_cube", RED), cube("blue_cube", BLUE), cube("green_cube", GREEN)
    steps = (pick_steps(red, "red_cube", 0.1) + place_steps(red, blue, "blue_cube", 0.06)
             + pick_steps(green, "green_cube", 0.14) + place_steps(green, red, "red_cube", 0.06) + [{"duration": 0.5}])
    return Task(
        "stack_three", "stack", "Stack the red cube on the blue cube, then the green cube on the red cube.",
        ["Build a tower: blue at the bottom, then red, then green.", "Put red on blue and green on red."],
        [obj(blue, x=(0.02, 0.08), y=(-0.1, -0.04)), obj(red, x=(-0.1, -0.04), y=(0.0, 0.04)), obj(green, x=(-0.04, 0.02), y=(0.07, 0.11))],
        "on(red_cube, blue_cube) and on(green_cube, red_cube) and at_rest(green_cube)",
        [{"object": "red_cube", "kind": "grasp"}, {"object": "blue_cube", "kind": "place"},
         {"object": "green_cube", "kind": "grasp"}, {"object": "red_cube", "kind": "place"}], steps,
    )


def cube_on_can() -> Task:
    steps = pick_steps(CUBE, "cube", 0.13) + place_steps(CUBE, CAN, "can", 0.05) + [{"duration": 0.5}]
    return Task(
        "stack_cube_on_can", "stack", "Put the red cube on top of the can.",
        ["Balance the cube on the can.", "Stack the red cube onto the can."],
        [obj(CUBE), obj(CAN, x=(0.02, 0.08), y=(-0.1, -0.05))], "on(cube, can) and at_rest(cube)",
        [{"object": "cube", "kind": "grasp"}, {"object": "can", "kind": "place"}], steps, robots=BIG_ARMS,
    )


def push(thing: Thing, small: bool = False) -> Task:
    """push {object} to the target; `small`: the SO-101 turns its narrow jaw broadside to the object"""
    height = 0.015 if thing.top <= 0.05 else 0.03  # m above the table: a tall thing pushed at its foot tips over, high it climbs the hand
    low = height - thing.base
    steps = [
        {"duration": 0.5, "gripper": "close"},
        {"duration": 1.5, "to_body": thing.name, "offset": [-0.07, 0, low + 0.08], **({"rotate": [0, 0, 1.5708]} if small else {})},
        {"duration": 0.8, "to_body": thing.name, "offset": [-0.07, 0, low]},
        {"duration": 2.5, "to_body": "target", "offset": [-0.035, 0, height]},
        {"duration": 0.8, "move": [-0.03, 0, 0.1]},
        {"duration": 0.5},
    ]
    target = {"name": "target", "box": [0.045, 0.045, 0.001], "rgba": [0.2, 0.75, 0.3, 0.6], "fixed": True, "collide": False,
              "region": {"x": [0.07, 0.09], "y": [-0.02, 0.02]}}
    return Task(
        f"push_{thing.name}", "push", f"Push the {the(thing.name)} onto the green square.",
        [f"Slide the {the(thing.name)} to the green target.", f"Push the {the(thing.name)} forward onto the green mark."],
        [obj(thing, x=(-0.07, -0.05), y=(-0.02, 0.02)), target], f"in_region({thing.name}, target) and at_rest({thing.name})",
        [{"object": thing.name, "kind": "push"}], steps, robots=thing.fits,
    )


DRAWER = {"name": "cabinet", "mjcf": f"{MESHES}/drawer_cabinet.xml", "fixed": True, "region": {"x": [0.13, 0.15], "y": [-0.03, 0.03]}}


def drawer(kind: str) -> Task:
    if kind == "open":
        steps = [
            {"duration": 1.5, "to_body": "drawer", "offset": [-0.13, 0, 0.11], "gripper": "open"},
            {"duration": 1.0, "to_body": "drawer", "offset": [-0.13, 0, 0.053]},
            {"duration": 0.6, "gripper": "close"},
            {"duration": 1.5, "move": [-0.1, 0, 0]},
            {"duration": 0.6, "gripper": "open"},
            {"duration": 0.8, "move": [0, 0, 0.08]},
            {"duration": 0.5},
        ]
        return Task("open_drawer", "drawer", "Open the drawer.", ["Pull the drawer open.", "Slide the drawer out by its handle."],
                    [dict(DRAWER)], "open(drawer_slide, 0.5)", [{"object": "drawer_handle", "kind": "grasp"}], steps, robots=BIG_ARMS)
    if kind == "close":
        steps = [
            {"duration": 0.5, "gripper": "close"},
            {"duration": 1.5, "to_body": "drawer", "offset": [-0.14, 0, 0.12]},
            {"duration": 1.0, "to_body": "drawer", "offset": [-0.14, 0, 0.085]},
            {"duration": 1.5, "move": [0.13, 0, 0]},
            {"duration": 0.8, "move": [-0.05, 0, 0.08]},
            {"duration": 0.5},
        ]
        return Task("close_drawer", "drawer", "Close the drawer.", ["Push the drawer shut.", "Slide the open drawer closed."],
                    [dict(DRAWER, joints={"drawer_slide": 0.11})], "closed(drawer_slide, 0.1)",
                    [{"object": "drawer", "kind": "push"}], steps, robots=BIG_ARMS)
    steps = pick_steps(CUBE, "cube", 0.16) + [
        {"duration": 1.5, "to_body": "drawer", "offset": [-0.035, 0, 0.17]},  # high: the drawer's front is 11 cm tall
        {"duration": 1.0, "to_body": "drawer", "offset": [-0.035, 0, 0.04]},
        {"duration": 0.6, "gripper": "open"},
        {"duration": 0.8, "move": [0, 0, 0.1]},
        {"duration": 0.5},
    ]
    return Task("put_cube_in_drawer", "drawer", "Put the red cube in the open drawer.",
                ["Place the cube into the drawer.", "Drop the red cube in the drawer."],
                [dict(DRAWER, joints={"drawer_slide": 0.12}), obj(CUBE, x=(-0.15, -0.09), y=(0.1, 0.15))],
                "inside(cube, drawer_inside) and at_rest(cube)",
                [{"object": "cube", "kind": "grasp"}, {"object": "drawer", "kind": "place"}], steps, robots=BIG_ARMS)


def open_cupboard() -> Task:
    steps = [
        {"duration": 1.5, "to_body": "cupboard_door", "offset": [-0.035, -0.2, 0.17], "gripper": "open"},
        {"duration": 1.0, "to_body": "cupboard_door", "offset": [-0.035, -0.2, 0.105]},
        {"duration": 0.6, "gripper": "close"},
        # three chords of the handle's arc (0.2 m about the hinge), the hand turning with the door: 60 degrees
        {"duration": 1.0, "move": [-0.0665, 0.024, 0], "rotate": [0, 0, -0.349]},
        {"duration": 1.0, "move": [-0.0545, 0.046, 0], "rotate": [0, 0, -0.349]},
        {"duration": 1.0, "move": [-0.035, 0.061, 0], "rotate": [0, 0, -0.349]},
        {"duration": 0.6, "gripper": "open"},
        {"duration": 0.8, "move": [0, 0, 0.1]},
        {"duration": 0.5},
    ]
    return Task("open_cupboard", "door", "Open the cupboard door.", ["Swing the cupboard door open by its handle.", "Pull the cupboard open."],
                [{"name": "cupboard", "mjcf": f"{MESHES}/cabinet_door.xml", "fixed": True, "region": {"x": [0.12, 0.14], "y": [0.0, 0.04]}}],
                "open(cupboard_hinge, 0.25)", [{"object": "cupboard_handle", "kind": "grasp"}], steps, robots=BIG_ARMS)


def sort_cubes() -> Task:
    red, blue = cube("red_cube", RED), cube("blue_cube", BLUE)
    bins = [mesh("basket", RED, 0.06 * 0.6, floor=0.006 * 0.6), mesh("basket", BLUE, 0.06 * 0.6, floor=0.006 * 0.6)]
    red_bin, blue_bin = (Thing(n, dict(b.fields, scale=0.6), b.top, floor=b.floor) for n, b in zip(("red_bin", "blue_bin"), bins))
    over_rim = red_bin.top - red_bin.floor + 0.008  # let go above the small bins' rims: open fingers would catch a wall
    steps = (pick_steps(red, "red_cube", 0.09) + place_steps(red, red_bin, "red_bin", 0.06, over_rim)
             + pick_steps(blue, "blue_cube", 0.09) + place_steps(blue, blue_bin, "blue_bin", 0.06, over_rim) + [{"duration": 0.5}])
    return Task(
        "sort_cubes", "sort", "Put the red cube in the red bin and the blue cube in the blue bin.",
        ["Sort the cubes into the bins by colour.", "Each cube goes into the bin of its colour."],
        [obj(red_bin, x=(0.06, 0.09), y=(0.07, 0.1)), obj(blue_bin, x=(0.06, 0.09), y=(-0.1, -0.07)),
         obj(red, x=(-0.1, -0.06), y=(-0.08, -0.03)), obj(blue, x=(-0.1, -0.06), y=(0.03, 0.08))],
        "inside(red_cube, red_bin) and inside(blue_cube, blue_bin)",
        [{"object": "red_cube", "kind": "grasp"}, {"object": "red_bin", "kind": "place"},
         {"object": "blue_cube", "kind": "grasp"}, {"object": "blue_bin", "kind": "place"}], steps,
    )


def upright_bottle() -> Task:
    steps = [
        {"duration": 1.5, "to_body": "bottle", "offset": [0, -0.06, 0.12], "rotate": [0, 0, 1.5708], "gripper": "open"},
        {"duration": 1.0, "to_body": "bottle", "offset": [0, -0.06, 0.0]},
        {"duration": 0.6, "gripper": "close"},
        {"duration": 1.0, "move": [0, 0, 0.15]},
        {"duration": 1.5, "rotate": [-1.5708, 0, 0]},
        {"duration": 1.0, "move": [0, 0, -0.105]},
        {"duration": 0.6, "gripper": "open"},
        {"duration": 0.8, "move": [0, 0.06, 0]},
        {"duration": 0.5},
    ]
    lying = obj(BOTTLE, x=(-0.04, 0.04), y=(0.04, 0.07))
    lying.update(euler=[math.pi / 2, 0.0, 0.0], z=0.028)  # on its side, neck toward -y
    return Task("stand_bottle_upright", "upright", "Stand the fallen bottle upright.",
                ["Pick up the bottle lying on its side and stand it up.", "Set the bottle upright on the table."],
                [lying], "upright(bottle, 0.2) and at_rest(bottle) and not grasped(bottle)",
                [{"object": "bottle", "kind": "grasp"}], steps, robots=BIG_ARMS)


def peg(shape: str) -> Task:
    hole = "square_hole" if shape == "square" else "round_hole"
    size = {"box": [0.012, 0.012, 0.03]} if shape == "square" else {"cylinder": [0.012, 0.03]}
    peg_entry = {"name": "peg", **size, "rgba": YELLOW, "region": {"x": [-0.1, -0.04], "y": [0.05, 0.1]}}
    peg_thing = Thing("peg", {}, 0.06, grasp=(0.0, 0.0, 0.045), base=0.03)
    steps = pick_steps(peg_thing, "peg", 0.1) + [
        {"duration": 1.5, "to_body": hole, "offset": [0, 0, 0.13]},
        {"duration": 1.0, "to_body": hole, "offset": [0, 0, 0.075]},
        {"duration": 0.5, "gripper": "open"},
        {"duration": 0.8, "move": [0, 0, 0.1]},
        {"duration": 0.5},
    ]
    fixture = {"name": hole, "mesh": f"{MESHES}/{hole}.obj", "scale": 1.0, "rgba": [0.3, 0.3, 0.35, 1.0], "fixed": True,
               "region": {"x": [0.02, 0.08], "y": [-0.1, -0.05]}}
    return Task(f"peg_in_{shape}_hole", "peg", f"Insert the {shape} peg into the {shape} hole.",
                [f"Put the {shape} peg in the hole.", f"Fit the yellow peg into the {shape} hole."],
                [peg_entry, fixture], f"in_region(peg, {hole}) and upright(peg, 0.3) and not lifted(peg, 0.01)",
                [{"object": "peg", "kind": "grasp"}, {"object": hole, "kind": "place"}], steps, robots=BIG_ARMS)


def library(small: bool = False) -> list[Task]:
    """Every task; `small` gives the SO-101's grasps where they differ (its jaw opens 21 mm)."""
    MUG = MUG_BY_RIM if small else globals()["MUG"]
    tasks = [pick_place(CUBE, BOWL, "in"), pick_place(CUBE, PLATE, "on"), pick_place(CUBE, BASKET, "in"),
             pick_place(MUG, BASKET, "in", x=(-0.1, -0.06), y=(0.06, 0.1)), pick_place(CUP, BASKET, "in"), pick_place(CAN, BASKET, "in"),
             pick_place(BOTTLE, BASKET, "in"), pick_place(MUG, PLATE, "on"), pick_place(CUP, PLATE, "on"),
             pick_place(CAN, PLATE, "on"), pick_place(BOWL, PLATE, "on"), pick_place(CAN, BOWL, "in")]
    tasks += [lift(t) for t in (MUG, CUP, BOWL, BOTTLE, CAN)] + [lift_at_any_yaw(L_BLOCK, "L-shaped block")]
    tasks += [stack_three(), cube_on_can(), push(CUBE, small), push(CAN), drawer("open"), drawer("close"), drawer("cube"),
              open_cupboard(), sort_cubes(), upright_bottle(), peg("square"), peg("round")]
    return tasks


# --- output -------------------------------------------------------------------------------------------

def _toml_value(value) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, (int, float)):
        return repr(round(float(value), 6)) if isinstance(value, float) else str(value)
    if isinstance(value, str):
        return json.dumps(value)
    if isinstance(value, (list, tuple)):
        return "[" + ", ".join(_toml_value(v) for v in value) + "]"
    if isinstance(value, dict):
        return "{" + ", ".join(f"{k} = {_toml_value(v)}" for k, v in value.items()) + "}"
    raise TypeError(type(value))


def task_toml(task: Task) -> str:
    lines = [f"# {task.family} family; generated by scenes/library/make_library.py (edit the template, not this file)",
             f"name = {_toml_value(task.name)}", f"family = {_toml_value(task.family)}",
             f"instruction = {_toml_value(task.instruction)}", f"instructions = {_toml_value(task.instructions)}",
             f"robots = {_toml_value(list(task.robots))}", "scale = \"robot\"",
             f"success = {_toml_value(task.success)}", f"hold = {_toml_value(task.hold)}",
             f"script = {_toml_value('../scripts/' + task.name + '.json')}",
             f"subtasks = {_toml_value(task.subtasks)}"]
    for entry in task.objects:
        lines += ["", "[[object]]"] + [f"{k} = {_toml_value(v)}" for k, v in entry.items()]
    return "\n".join(lines) + "\n"


def scaled_steps(steps: list[dict], scale: float) -> list[dict]:
    out = []
    for step in steps:
        step = dict(step)
        for key in ("move", "offset", "to"):
            if key in step:
                step[key] = [round(v * scale, 4) for v in step[key]]
        out.append(step)
    return out


def script_text(steps: list[dict]) -> str:
    return '{"steps": [\n' + ",\n".join("  " + json.dumps(s) for s in steps) + "\n]}\n"


def write_library(out: Path = HERE, scripts: Path = SCRIPTS) -> list[Path]:
    written = []
    small = {task.name: task for task in library(small=True)}
    for task in library():
        path = out / f"{task.name}.toml"
        path.write_text(task_toml(task))
        written.append(path)
        (scripts / f"{task.name}.json").write_text(script_text(task.steps))
        written.append(scripts / f"{task.name}.json")
        if "so101" in task.robots:
            (scripts / f"{task.name}.so101.json").write_text(script_text(scaled_steps(small[task.name].steps, SO101_SCALE)))
            written.append(scripts / f"{task.name}.so101.json")
    return written


if __name__ == "__main__":
    for p in write_library():
        print(p)
