"""`--plan-url URL`: an OpenAI-compatible chat-completions endpoint (a local model server) writes the plan.

It gets the instruction and the perceived objects and must answer the steps in the scripts' JSON
(`{"steps": [...]}`, devices/script.py), which are validated exactly like a script file: an answer
that is not one is a ScriptError naming the step and field (one line, exit 2).
"""

from __future__ import annotations

import json
import re
import urllib.error
import urllib.request
from collections.abc import Sequence

from devices.script import ScriptStep, parse_script
from scenes.errors import TeleopError
from teleop.instruct.grammar import colour_word
from teleop.instruct.perceive import SceneObject
from teleop.instruct.planner import Located

TIMEOUT_S = 120.0

PROMPT = """You plan robot arm motions. Answer only a JSON object {"steps": [...]} for a parallel-gripper arm.
Each step: "duration" (s, required), and any of: "to" [x, y, z] (m, world, the hand's target), "move" [dx, dy, dz] (m),
"orient" [roll, pitch, yaw] (rad; the hand points down at [3.14159, 0, yaw]), "gripper" "open" | "close".
Grasp an object at its position with the gripper open, approaching from 0.12 m above; lift 0.15 m after closing;
release 0.012 m above the top it goes on. End with {"duration": 0.5}."""


class PlanUrlError(TeleopError):
    """The endpoint could not be reached or answered no plan; one line."""


def chat_url(url: str) -> str:
    """The chat-completions address of a server's base URL (".../v1" or the full address both work)."""
    url = url.rstrip("/")
    return url if url.endswith("/chat/completions") else url + "/chat/completions"


def request_body(instruction: str, objects: Sequence[SceneObject], where: dict[str, Located], home: Sequence[float],
                 model: str = "default") -> dict:
    seen = [
        {"name": o.name, "colour": colour_word(o.rgba), "shape": o.shape, **where[o.name].as_json()}
        for o in objects if o.name in where
    ]
    user = json.dumps({"instruction": instruction, "objects": seen, "home": [round(float(v), 4) for v in home]})
    return {"model": model, "temperature": 0, "messages": [{"role": "system", "content": PROMPT}, {"role": "user", "content": user}]}


def answer_text(reply: dict, url: str) -> str:
    """The first choice's message content, with a Markdown code fence around it taken off."""
    try:
        content = reply["choices"][0]["message"]["content"]
    except (KeyError, IndexError, TypeError):
        raise PlanUrlError(f"--plan-url {url}: the answer is not a chat completion (no choices[0].message.content)") from None
    if not isinstance(content, str):
        raise PlanUrlError(f"--plan-url {url}: the answer's message content is not text")
    fenced = re.search(r"```(?:json)?\s*(.*?)```", content, re.S)
    return fenced.group(1) if fenced else content


def plan_from_url(url: str, instruction: str, objects: Sequence[SceneObject], where: dict[str, Located],
                  home: Sequence[float]) -> tuple[list[ScriptStep], list[dict]]:
    """(validated steps, the steps as JSON) the endpoint answered."""
    body = json.dumps(request_body(instruction, objects, where, home)).encode()
    req = urllib.request.Request(chat_url(url), data=body, headers={"Content-Type": "application/json"}, method="POST")
    try:
        with urllib.request.urlopen(req, timeout=TIMEOUT_S) as resp:
            reply = json.loads(resp.read().decode("utf-8", "replace"))
    except urllib.error.HTTPError as exc:
        raise PlanUrlError(f"--plan-url {url}: the server answered HTTP {exc.code}") from None
    except (urllib.error.URLError, OSError) as exc:
        raise PlanUrlError(f"--plan-url {url}: cannot reach it ({getattr(exc, 'reason', exc)})") from None
    except json.JSONDecodeError:
        raise PlanUrlError(f"--plan-url {url}: the answer is not JSON") from None
    text = answer_text(reply, url)
    steps = parse_script(text, f"the plan from {url}")
    return steps, json.loads(text)["steps"]
