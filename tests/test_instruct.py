"""A sentence to a demonstration (issue 59, items 2-3): the library's own instructions solved from perception,
a sentence that names what the scene lacks refused in one line, paraphrases planned alike, the plan noted in the
episode (which replays bit for bit), and `--plan-url` against a chat-completions server written here."""

from __future__ import annotations

import json
import threading
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer

import pytest

from devices.registry import split_spec
from scenes.tasks.registry import find_task
from teleop.instruct.grammar import Action, GroundingError, parse
from teleop.instruct.perceive import scene_objects
from tests.support import assert_one_line_error, run_cli

EPISODES = "5"


def objects(scene: str):
    return scene_objects(find_task(scene))


@pytest.mark.e2e
@pytest.mark.parametrize("scene", ["lift", "stack", "pick_place", "push_cube"])
def test_the_library_instruction_succeeds_from_perception(scene, tmp_path):
    task = find_task(scene)
    args = ["run", "--device", f"instruct:{task.text}", "--scene", scene, "--episodes", EPISODES, "--json"]
    if scene == "stack":
        args += ["--record", str(tmp_path / "rec")]
    result = run_cli(*args)
    assert result.returncode == 0, result.stderr[-2000:]
    out = json.loads(result.stdout)
    assert [e["success"] for e in out["per_episode"]] == [True] * int(EPISODES), out["per_episode"]
    assert out["devices"] == ["instruct"]
    if scene == "stack":
        import teleop

        assert all(e["replay_bit_exact"] for e in out["per_episode"])
        first, second = (teleop.load_episode(f).meta for f in sorted(out["files"])[:2])
        note = first.generator
        assert note["name"] == "teleop.instruct" and note["instruction"] == task.text and note["positions"] == "camera:front"
        assert note["actions"] == ["place cube on cube_base"]
        assert set(note["objects"]) == {"cube", "cube_base"} and note["objects"]["cube"]["status"] == "visible"
        assert note["objects"]["cube"]["position"] != second.generator["objects"]["cube"]["position"]  # planned per seed
        assert first.source == "script" and first.devices == ("instruct",)


@pytest.mark.e2e
def test_positions_from_the_state_for_comparison():
    result = run_cli("run", "--device", "instruct:put the red cube into the grey bin", "--scene", "pick_place", "--seed", "3",
                     "--instruct-state", "--json")
    assert result.returncode == 0, result.stderr[-2000:]
    assert json.loads(result.stdout)["success"] is True


def test_a_sentence_naming_a_missing_object_is_one_line():
    result = run_cli("run", "--device", "instruct:put the green ball on the red cube", "--scene", "stack", "--json")
    assert_one_line_error(result, "green ball", "red cube", "blue cube base")
    assert json.loads(result.stdout)["error"].startswith("no green ball")


@pytest.mark.unit
def test_a_paraphrase_gives_the_same_plan():
    stack = objects("stack")
    expected = [Action("place", "cube", "cube_base", "on")]
    assert parse(find_task("stack").text, stack) == expected
    assert parse("stack the red block onto the blue one", stack) == expected
    assert parse("Put the red cube on top of the blue cube.", stack) == expected
    for scene, first in (("lift", [Action("pick", "cube")]), ("push_cube", [Action("push", "cube", "target")]),
                         ("pick_place", [Action("place", "cube", "bin", "in")])):
        task = find_task(scene)
        for sentence in (task.text, *task.instructions):
            assert parse(sentence, objects(scene)) == first, sentence


@pytest.mark.unit
def test_the_grammar_reads_sequences_and_refuses_what_it_cannot_ground():
    sort = parse(find_task("sort_cubes").text, objects("sort_cubes"))  # the verb carries over to the second clause
    assert sort == [Action("place", "red_cube", "red_bin", "in"), Action("place", "blue_cube", "blue_bin", "in")]
    lift = parse("pick up the red cube, then open the gripper and go home", objects("lift"))
    assert [a.kind for a in lift] == ["pick", "open", "home"]
    with pytest.raises(GroundingError, match="could be any of"):
        parse("pick up the cube", objects("stack"))  # two cubes: say which
    with pytest.raises(GroundingError, match="cannot read"):
        parse("dance with the red cube", objects("lift"))


@pytest.mark.unit
def test_an_instruct_sentence_keeps_its_commas_in_a_device_list():
    assert split_spec("keyboard, instruct:pick up the cube, then go home") == ["keyboard", "instruct:pick up the cube, then go home"]
    assert split_spec("keyboard,gizmo") == ["keyboard", "gizmo"]


class ChatServer(BaseHTTPRequestHandler):
    """An OpenAI-compatible chat-completions endpoint: it reads the instruction and the perceived objects it is
    sent and answers a pick-and-lift plan for the object the instruction names, at the position it was told
    (under /bad/: a plan with a gripper word no script has)."""

    requests: list[dict] = []

    def do_POST(self) -> None:  # noqa: N802 - http.server's name
        body = json.loads(self.rfile.read(int(self.headers["Content-Length"])))
        ChatServer.requests.append({"path": self.path, **body})
        told = json.loads(body["messages"][-1]["content"])
        target = next(o for o in told["objects"] if o["name"] in told["instruction"])
        x, y, z = target["position"]
        steps = [
            {"duration": 1.5, "to": [x, y, z + 0.12], "orient": [3.14159, 0, 0], "gripper": "open"},
            {"duration": 1.0, "to": [x, y, z]},
            {"duration": 0.6, "gripper": "close" if not self.path.startswith("/bad/") else "squeeze"},
            {"duration": 1.2, "move": [0, 0, 0.15]},
            {"duration": 0.5},
        ]
        content = "Here is the plan:\n```json\n" + json.dumps({"steps": steps}) + "\n```"
        reply = json.dumps({"id": "chat-1", "object": "chat.completion", "model": body.get("model"),
                            "choices": [{"index": 0, "message": {"role": "assistant", "content": content}, "finish_reason": "stop"}]})
        self.send_response(200)
        self.send_header("Content-Type", "application/json")
        self.send_header("Content-Length", str(len(reply)))
        self.end_headers()
        self.wfile.write(reply.encode())

    def log_message(self, *args) -> None:
        pass


@pytest.fixture(scope="module")
def chat_url():
    server = ThreadingHTTPServer(("127.0.0.1", 0), ChatServer)
    thread = threading.Thread(target=server.serve_forever, daemon=True)
    thread.start()
    yield f"http://127.0.0.1:{server.server_address[1]}"
    server.shutdown()
    server.server_close()


@pytest.mark.e2e
def test_a_plan_from_a_chat_endpoint_is_validated_and_executed(chat_url):
    ChatServer.requests.clear()
    ok = run_cli("run", "--device", "instruct:lift the cube", "--scene", "lift", "--plan-url", f"{chat_url}/v1", "--json")
    assert ok.returncode == 0, ok.stderr[-2000:]
    assert json.loads(ok.stdout)["success"] is True
    sent = ChatServer.requests[-1]
    assert sent["path"] == "/v1/chat/completions" and sent["messages"][0]["role"] == "system"
    told = json.loads(sent["messages"][-1]["content"])
    assert told["instruction"] == "lift the cube" and told["objects"][0]["name"] == "cube"
    assert len(told["objects"][0]["position"]) == 3 and told["home"]
    bad = run_cli("run", "--device", "instruct:lift the cube", "--scene", "lift", "--plan-url", f"{chat_url}/bad/v1")
    assert_one_line_error(bad, "step 3", "gripper")
    gone = run_cli("run", "--device", "instruct:lift the cube", "--scene", "lift", "--plan-url", "http://127.0.0.1:9/v1")
    assert_one_line_error(gone, "--plan-url", "cannot reach")


@pytest.mark.e2e
def test_the_browser_session_plays_an_instruction(tmp_path):
    """`teleop serve --device instruct:...` plans from the camera when the session starts and the arm carries it out."""
    from tests.browser import ServeProcess

    server = ServeProcess(["--device", "instruct:pick up the red cube", "--scene", "lift", "--seed", "2"], tmp_path)
    try:
        status = server.wait_for(lambda s: s["success"] and s["objects"]["cube"][2] > 0.05, timeout_s=120, what="the cube lifted")
        word = status["devices"]["instruct"]  # its status, or the line that stopped it
        assert word == "done" or word.startswith("step "), word
    finally:
        assert server.stop() in (0, 130), server.log()[-2000:]
