"""The XR page's server side without a browser: the scene and poses messages, the placement, the page's
messages and the `xr` device's clutch and safety rules, on real sessions (MuJoCo, the controller's IK)."""

from __future__ import annotations

import math
import time
from pathlib import Path

import mujoco
import numpy as np
import pytest

from teleop.control.session import Session
from teleop.web.xr_page.scene_message import poses_message, read_errors, read_poses, read_scene_header, scene_message
from teleop.web.xr_page.xr_device import MAX_STEP_M, XrDevice
from teleop.web.xr_page.xr_messages import Rejected, XrPose, parse

pytestmark = pytest.mark.unit
UP = (1.0, 0.0, 0.0, 0.0)
ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def panda():
    session = Session("lift", "panda", seed=0)
    yield session
    session.close()


@pytest.fixture(scope="module")
def rig():
    session = Session("handover", "bimanual", seed=0)
    yield session
    session.close()


def _bases(session):
    c = session.controller
    return [c.base_pose(i) for i in range(c.n_arms)]


def test_the_scene_message_holds_the_shown_geoms_and_where_the_operator_stands(panda):
    model = panda.controller.model
    message = scene_message(model, _bases(panda), 1)
    head = read_scene_header(message)
    assert head["bodies"] == model.nbody and head["arms"] == 1
    table = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_GEOM, "table")
    boxes = [g for g in head["geoms"] if g["type"] == "box" and g["body"] == int(model.geom_bodyid[table])]
    assert any(np.allclose(g["size"], model.geom_size[table], atol=1e-6) for g in boxes)
    robot_bodies = {g["body"] for g in head["geoms"] if model.body(g["body"]).name.startswith(("link", "hand", "left_finger"))}
    assert len(robot_bodies) >= 5, "the arm's links are drawn"
    place = head["placement"]
    base = _bases(panda)[0][0]
    assert np.allclose(place["stand"][:2], base[:2], atol=1e-6) and abs(place["yaw"]) < 1e-6  # at the base, facing +x
    top = float(model.geom_pos[table][2] + model.geom_size[table][2])
    assert place["stand"][2] == pytest.approx(top, abs=1e-6) and place["headset_above_m"] == 0.45


def test_meshes_travel_as_float_vertices_and_uint_triangles():
    session = Session(str(ROOT / "scenes" / "library" / "lift_bottle.toml"), "panda", seed=0)  # a mesh bottle
    try:
        model = session.controller.model
        message = scene_message(model, _bases(session), 1)
    finally:
        session.close()
    head = read_scene_header(message)
    data = 8 + len(message[8:8 + int.from_bytes(message[4:8], "little")])
    assert head["meshes"], "the bottle is a mesh"
    mesh_id, entry = next(iter(head["meshes"].items()))
    m = int(mesh_id)
    verts = np.frombuffer(message, "<f4", entry["nvert"] * 3, data + entry["vert"]).reshape(-1, 3)
    faces = np.frombuffer(message, "<u4", entry["nface"] * 3, data + entry["face"]).reshape(-1, 3)
    v0, f0 = model.mesh_vertadr[m], model.mesh_faceadr[m]
    assert np.array_equal(verts, model.mesh_vert[v0:v0 + entry["nvert"]].astype("<f4"))
    assert np.array_equal(faces, model.mesh_face[f0:f0 + entry["nface"]])


def test_the_two_arm_rig_puts_the_operator_at_the_long_side_with_arm_0_on_the_left(rig):
    head = read_scene_header(scene_message(rig.controller.model, _bases(rig), 2))
    place = head["placement"]
    facing = np.array([math.cos(place["yaw"]), math.sin(place["yaw"])])
    left = np.array([-facing[1], facing[0]])
    stand = np.array(place["stand"][:2])
    (b0, _), (b1, _) = _bases(rig)
    assert (b0[:2] - stand) @ left > 0.1 and (b1[:2] - stand) @ left < -0.1
    middle = (b0[:2] + b1[:2]) / 2
    assert (middle - stand) @ facing > 0.1, "the table is ahead"
    assert abs((middle - stand) @ left) < 1e-6, "at the middle of the side"


def test_the_poses_message_carries_every_body_and_each_arms_force(panda):
    data = panda.controller.data
    message = poses_message(7, 1.25, data.xpos, data.xquat, 42, np.array([3.5]), np.array([0.03]))
    tick, sim_time, frame, poses, forces = read_poses(message)
    assert read_errors(message).tolist() == pytest.approx([0.03])
    assert (tick, sim_time, frame) == (7, 1.25, 42)
    assert np.allclose(poses[:, :3], data.xpos, atol=1e-6) and np.allclose(poses[:, 3:], data.xquat, atol=1e-6)
    assert forces.tolist() == [3.5]


def _pose(device, hand, pos, quat=UP, clutch=True, opening=None, frame=0):
    return device.push_pose(hand, frame, True, list(pos), list(quat), clutch, opening)


def _apply(session, commands):
    """Run the commands through the controller (its targets) as the loop does."""
    session.controller.step(commands)


def test_the_clutch_applies_motion_since_the_press_and_never_moves_the_arm_while_up(panda):
    c = panda.controller
    device = XrDevice(n_arms=1)
    start_pos, start_quat = (np.array(v) for v in c.target_pose(0))
    _pose(device, "right", [1.0, 2.0, 1.0])
    assert device.poll(c, c.dt) == [], "engaging moves nothing"
    _pose(device, "right", [1.03, 2.0, 1.0])
    (command,) = device.poll(c, c.dt)
    assert command.source == "xr" and command.arm == 0
    assert np.allclose(command.target_pos, start_pos + [0.03, 0, 0], atol=1e-9)
    assert np.allclose(command.target_quat, start_quat, atol=1e-9)
    _apply(panda, [command])
    _pose(device, "right", [1.03, 2.0, 1.0], clutch=False)
    _pose(device, "right", [0.9, 2.0, 1.0], clutch=False)  # moved back with the clutch up
    assert device.poll(c, c.dt) == []
    _pose(device, "right", [0.9, 2.0, 1.0])  # pressed again: motion counts from here
    assert device.poll(c, c.dt) == []
    _pose(device, "right", [0.9, 2.02, 1.0])
    (command,) = device.poll(c, c.dt)
    assert np.allclose(command.target_pos, start_pos + [0.03, 0.02, 0], atol=1e-9)
    half = math.sqrt(0.5)
    _pose(device, "right", [0.9, 2.02, 1.0], quat=[half, half, 0, 0])  # 90 degrees about world x
    (command,) = device.poll(c, c.dt)
    turned = np.empty(4)
    mujoco.mju_mulQuat(turned, np.array([half, half, 0, 0]), start_quat)
    assert np.allclose(command.target_quat, turned, atol=1e-9)


def test_the_left_hand_is_free_on_one_arm_and_drives_arm_0_of_two(panda, rig):
    one, two = XrDevice(n_arms=1), XrDevice(n_arms=2)
    for device in (one, two):
        for hand in ("left", "right"):
            _pose(device, hand, [0, 1, 0])
    assert one.poll(panda.controller, 0.03) == [] and two.poll(rig.controller, 0.03) == []
    for device in (one, two):
        for hand, dx in (("left", 0.01), ("right", 0.02)):
            _pose(device, hand, [dx, 1, 0])
    assert [c.arm for c in one.poll(panda.controller, 0.03)] == [0]
    commands = two.poll(rig.controller, 0.03)
    assert sorted(c.arm for c in commands) == [0, 1]
    for c in commands:
        start = rig.controller.target_pose(c.arm)[0]
        assert np.allclose(c.target_pos - start, [0.01 if c.arm == 0 else 0.02, 0, 0], atol=1e-9)


def test_nan_absurd_and_lost_poses_are_dropped_counted_and_let_go(panda):
    c = panda.controller
    device = XrDevice(n_arms=1)
    _pose(device, "right", [0, 1, 0])
    device.poll(c, c.dt)
    assert device.engaged()["right"]
    assert device.push_pose("right", 1, True, [None, 1.0, 0.0], list(UP), True, None) is False  # NaN, as JSON's null
    assert device.poll(c, c.dt) == [] and not device.engaged()["right"]
    assert device.push_pose("right", 2, True, [1e6, 1.0, 0.0], list(UP), True, None) is False  # absurd
    assert device.push_pose("right", 3, True, [0, 1.0, 0.0], [2.0, 0, 0, 0], True, None) is False  # not a rotation
    assert device.counts.bad_poses == 3 and device.counts.releases["bad pose"] == 1
    _pose(device, "right", [0.2, 1, 0])  # good again, clutch still held: taken from here, no jump
    assert device.poll(c, c.dt) == [] and device.engaged()["right"]
    device.push_pose("right", 4, False, None, None, True, None)  # tracking lost
    assert device.counts.releases["tracking lost"] == 1 and device.poll(c, c.dt) == []
    _pose(device, "right", [0.2, 1, 0])
    device.poll(c, c.dt)
    device.release("blurred")
    assert device.counts.releases["blurred"] == 1 and not device.engaged()["right"]


def test_no_pose_for_a_quarter_second_lets_go(panda):
    c = panda.controller
    device = XrDevice(n_arms=1)
    _pose(device, "right", [0, 1, 0])
    device.poll(c, c.dt)
    time.sleep(0.3)
    assert device.poll(c, c.dt) == [] and not device.engaged()["right"]
    assert device.counts.releases["no pose"] == 1


def test_a_target_jump_over_5_cm_is_refused_and_counted(panda):
    c = panda.controller
    device = XrDevice(n_arms=1)
    start = np.array(c.target_pose(0)[0])
    _pose(device, "right", [0, 1, 0])
    device.poll(c, c.dt)
    _pose(device, "right", [MAX_STEP_M + 0.02, 1, 0])
    assert device.poll(c, c.dt) == [] and device.counts.jumps == 1
    _pose(device, "right", [MAX_STEP_M + 0.03, 1, 0])  # from where the hand was refused, not from the press
    (command,) = device.poll(c, c.dt)
    assert np.allclose(command.target_pos, start + [0.01, 0, 0], atol=1e-9)


def test_buttons_and_the_trigger(panda):
    c = panda.controller
    device = XrDevice(n_arms=1)
    device.press("right", "a")
    device.press("right", "b")
    device.press("left", "y")  # the page's: recentre
    assert [cmd.events for cmd in device.poll(c, c.dt)] == [("record",), ("discard",)]
    _pose(device, "right", [0, 1, 0], clutch=False, opening=0.25)
    (command,) = device.poll(c, c.dt)
    assert command.gripper_opening == 0.25 and command.target_pos is None
    _pose(device, "right", [0, 1, 0], clutch=False, opening=0.25)
    assert device.poll(c, c.dt) == [], "an unchanged trigger is not sent again"


def test_the_page_messages_are_checked():
    pose = parse('{"type":"xr_pose","hand":"right","frame":3,"t":1.5,"tracked":true,"pos":[0,1,null],'
                 '"quat":[1,0,0,0],"clutch":true,"opening":0.5,"mode":"controller"}')
    assert isinstance(pose, XrPose) and pose.pos == (0.0, 1.0, None)
    for bad in ('{"type":"xr_pose"}', '{"type":"xr_button","hand":"right","button":"z"}', '{"type":"xr_config","scale":50}',
                '{"type":"xr_release","why":"bored"}', "[1]", '{"type":"xr_config","scale":NaN}', "x" * 600):
        with pytest.raises(Rejected):
            parse(bad)


def test_a_page_that_closes_lets_go_and_its_bad_messages_are_counted():
    """The channel on a real websockets server: a pose with the clutch held, a bad message, then the page closes."""
    import asyncio
    import threading

    from websockets.asyncio.server import serve
    from websockets.sync.client import connect

    from teleop.web.xr_page.xr_channel import XrChannel

    device = XrDevice(n_arms=1)
    channel = XrChannel(device, lambda generation: b"")
    ready, stop = threading.Event(), None
    port = []

    async def run():
        nonlocal stop
        stop = asyncio.get_running_loop().create_future()
        async with serve(channel.handle, "127.0.0.1", 0) as server:
            port.append(server.sockets[0].getsockname()[1])
            ready.set()
            await stop

    loop = asyncio.new_event_loop()
    thread = threading.Thread(target=loop.run_until_complete, args=(run(),), daemon=True)
    thread.start()
    assert ready.wait(10)
    try:
        with connect(f"ws://127.0.0.1:{port[0]}") as ws:
            ws.send('{"type":"xr_pose","hand":"right","frame":1,"t":0,"tracked":true,"pos":[0,1,0],'
                    '"quat":[1,0,0,0],"clutch":true,"opening":null,"mode":"controller"}')
            ws.send('{"type":"xr_pose","hand":"middle"}')
            deadline = time.monotonic() + 10
            while channel.accepted + channel.dropped < 2 and time.monotonic() < deadline:
                time.sleep(0.01)
        deadline = time.monotonic() + 10
        while "page closed" not in device.counts.releases and time.monotonic() < deadline:
            time.sleep(0.01)
        assert channel.accepted == 1 and channel.dropped == 1 and "xr_pose" in channel.last_drop
        assert device.counts.releases.get("page closed") == 1 and device.poses == 1
    finally:
        loop.call_soon_threadsafe(stop.set_result, None)
        thread.join(10)
