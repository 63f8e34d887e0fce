"""Issue 38, items 1, 2 and 6: a task file is refused when it is read, in one line naming the file, the
object and the field: a size or mesh scale that is not positive, objects that overlap on some seeds
(`teleop scenes FILE` tries many, `--seeds N`), a bad mesh named as the file names it. In-process and quick."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from scenes.assembly.arena import reference_layout
from scenes.tasks.file_task import load_task_file
from scenes.tasks.file_values import TaskFileError
from scenes.tasks.placement import PlacementError
from scenes.tasks.seed_check import DEFAULT_SEEDS, check_placement
from teleop.cli.entry import main

pytestmark = pytest.mark.unit

ONE_BOX = '''
name = "checks"
instruction = "Lift the thing."
robots = ["panda"]
success = "lifted(thing, 0.05)"

[[object]]
name = "thing"
{shape}
'''


def write(tmp_path: Path, text: str) -> Path:
    path = tmp_path / "checks.toml"
    path.write_text(text)
    return path


def refusal(path: Path) -> str:
    with pytest.raises(TaskFileError) as info:
        load_task_file(path)
    message = str(info.value)
    assert "\n" not in message and "does not compile" not in message
    return message


@pytest.mark.parametrize("shape,field", [
    ("box = [0.02, -0.02, 0.02]", "box"),
    ("box = [0.02, 0.0, 0.02]", "box"),
    ('box = ["1 size", "-1 size", "1 size"]', "box"),
    ("cylinder = [-0.02, 0.04]", "cylinder"),
    ("sphere = 0", "sphere"),
    ("capsule = [0.02, -0.03]", "capsule"),
    ("bin = [0.06, 0.06, -0.03]", "bin"),
    ("bin = [0.06, 0.06, 0.03]\nwall = -0.004", "wall"),
])
def test_a_size_that_is_not_positive_is_refused_when_read_naming_the_object_and_field(tmp_path, shape, field):
    path = write(tmp_path, ONE_BOX.format(shape=shape))
    message = refusal(path)
    assert message.startswith(f"{path}: [[object]] 'thing': {field}: "), message
    assert "must be > 0" in message


def test_positive_sizes_in_every_unit_still_load(tmp_path):
    task = load_task_file(write(tmp_path, ONE_BOX.format(shape='box = ["1 size", 0.02, "0.02 m"]')))
    assert [o.shape for o in task.objects] == ["box"]


def make_mesh(folder: Path) -> None:
    """A closed tetrahedron (m): a mesh with volume."""
    (folder / "meshes").mkdir(exist_ok=True)
    (folder / "meshes" / "tet.obj").write_text("v 0 0 0\nv 0.04 0 0\nv 0 0.04 0\nv 0 0 0.04\nf 1 3 2\nf 1 2 4\nf 1 4 3\nf 2 3 4\n")
    (folder / "meshes" / "garbage.obj").write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n")  # flat: no volume


@pytest.mark.parametrize("scale", ["-1.0", "0", "[1.0, 1.0, -1.0]"])
def test_a_mesh_scale_that_is_not_positive_is_refused(tmp_path, scale):
    make_mesh(tmp_path)
    path = write(tmp_path, ONE_BOX.format(shape=f'mesh = "meshes/tet.obj"\nscale = {scale}'))
    message = refusal(path)
    assert message.startswith(f"{path}: [[object]] 'thing': scale: "), message
    assert "must be > 0" in message


def test_a_bad_mesh_is_named_as_the_task_file_names_it(tmp_path):
    make_mesh(tmp_path)
    path = write(tmp_path, ONE_BOX.format(shape='mesh = "meshes/garbage.obj"'))
    message = refusal(path)
    assert message == f"{path}: [[object]] 'thing': mesh: meshes/garbage.obj: has no triangles with volume"
    assert str(tmp_path / "meshes") not in message  # no absolute path to the mesh, no "mesh: mesh"


# -- placement over many seeds ---------------------------------------------------------------------------

CLASHING = '''
name = "clashing"
instruction = "Push the slider."
robots = ["panda"]
success = "at_rest(slider)"

[[object]]
name = "slider"
box = [0.02, 0.02, 0.02]
region = {x = [-0.3, 0.3], y = 0.0}

[[object]]
name = "post"
box = [0.02, 0.02, 0.02]
fixed = true
region = {x = 0.0, y = 0.0}
'''


def test_objects_that_overlap_on_some_seeds_are_refused_naming_them_and_the_share(tmp_path):
    path = write(tmp_path, CLASHING)
    task = load_task_file(path)  # seed 0 places apart: loading alone cannot tell
    check_placement(task, ["panda"], seeds=1)
    with pytest.raises(TaskFileError) as info:
        check_placement(task, ["panda"], seeds=DEFAULT_SEEDS)
    message = str(info.value)
    assert message.startswith(f"{path}: [[object]] 'post': region: cannot be placed apart from 'slider' on ")
    assert f"of {DEFAULT_SEEDS} seeds (" in message and "robot panda" in message
    share = float(message.split(" seeds (")[1].split("%")[0])
    assert 5.0 < share < 50.0  # the post's footprint over the slider's 60 cm range: about a fifth of the seeds
    first = int(message.split("first seed ")[1].split(",")[0])
    with pytest.raises(PlacementError):  # the seed it names fails as `teleop run --seed` would
        task.place(reference_layout(), np.random.default_rng(first))


def test_teleop_scenes_tries_the_seeds_and_seeds_sets_how_many(tmp_path, capsys):
    path = write(tmp_path, CLASHING)
    assert main(["scenes", str(path), "--json"]) == 2
    out, err = capsys.readouterr()
    assert "cannot be placed apart from 'slider'" in err and len(err.strip().splitlines()) == 1
    assert "error" in json.loads(out)
    assert main(["scenes", str(path), "--seeds", "1", "--json"]) == 0
    rows = json.loads(capsys.readouterr()[0])["scenes"]
    assert [(r["name"], r["robots"]) for r in rows] == [("clashing", ["panda"])]
    assert main(["scenes", str(path), "--seeds", "0"]) == 2
    assert "--seeds must be at least 1" in capsys.readouterr()[1]
