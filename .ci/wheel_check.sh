#!/usr/bin/env bash
# A normal install works: build the wheel (not editable), install it into a fresh venv and use it from
# outside the checkout: `teleop scenes`, a scripted `teleop run` that records, `teleop replay --verify`
# (bit-exact), and `teleop serve` answering / and /phone with HTTP 200.
#   .ci/wheel_check.sh [PYTHON]   (default: the test venv's python, for its pip cache and interpreter)
set -euo pipefail
# Only the fresh venv counts: a caller's PYTHONPATH naming a checkout (a test run pointed at its clone) would let
# pip take the package as installed already and the checks import the checkout's code
unset PYTHONPATH PYTHONHOME
root=$(cd "$(dirname "$0")/.." && pwd)
python=${1:-$root/.venv/bin/python}
case "$python" in /*) ;; */*) python="$PWD/$python" ;; esac  # a relative path (run.sh's .venv/bin/python) outlives the cd below
work=$(mktemp -d)
serve_pid=""
cleanup() { [ -n "$serve_pid" ] && kill "$serve_pid" 2>/dev/null; rm -rf "$work"; }
trap cleanup EXIT
say() { echo "wheel check: $*" >&2; }
fail() { say "FAILED: $*"; exit 1; }
# From a clean copy: setuptools' build/ folder in the checkout could hold files of an earlier build.
mkdir "$work/src"
(cd "$root" && git ls-files -co --exclude-standard | while read -r f; do [ -f "$f" ] && printf '%s\0' "$f"; done) \
    | (cd "$root" && xargs -0 cp --parents -t "$work/src")
"$python" -m pip wheel --no-deps --no-build-isolation -q "$work/src" -w "$work/dist" || fail "pip wheel could not build the package"
wheel=$(ls "$work"/dist/mujoco_teleop-*.whl)
say "built $(basename "$wheel")"
"$python" -m venv "$work/venv" || fail "python -m venv failed"
"$work/venv/bin/python" -m pip install -q "$wheel" || fail "pip install of the wheel (core dependencies only) failed"
say "installed it (not editable) into a fresh venv"
teleop="$work/venv/bin/teleop"
cd "$work"  # outside the checkout: only the installed package can be found
site=$("$work/venv/bin/python" -c 'import scenes, pathlib; print(pathlib.Path(scenes.__file__).parent)')
case "$site" in "$work/venv/"*) ;; *) fail "scenes was imported from $site, not from the fresh venv";; esac
export MUJOCO_GL=${MUJOCO_GL:-egl}
scenes=$("$teleop" scenes) || fail "teleop scenes exited with $?"
grep -q '^lift' <<< "$scenes" || fail "teleop scenes does not list lift: $scenes"
[ "$(wc -l <<< "$scenes")" -ge 30 ] || fail "teleop scenes lists fewer than 30 tasks (the library's files are missing?)"
"$teleop" run --device "script:$site/scripts/put_mug_in_basket.json" --scene put_mug_in_basket --json > "$work/mug.json" \
    || fail "teleop run of a library task (a mesh object) exited with $?"
grep -q '"success": true' "$work/mug.json" || fail "the library task's script did not succeed: $(cat "$work/mug.json")"
say "teleop scenes: ok"
"$teleop" run --device "script:$site/scripts/lift_pick.json" --scene lift --record "$work/eps" --json > "$work/run.json" \
    || fail "teleop run (scripted, recording) exited with $?"
grep -q '"success": true' "$work/run.json" || fail "the scripted run did not succeed: $(cat "$work/run.json")"
say "teleop run --device script:.../lift_pick.json --record: ok (success)"
"$teleop" replay "$work/eps/episode_000000.mcap" --verify --json > "$work/verify.json" \
    || fail "teleop replay --verify exited with $?: $(cat "$work/verify.json")"
grep -q '"bit_exact": true' "$work/verify.json" || fail "the replay is not bit-exact: $(cat "$work/verify.json")"
say "teleop replay --verify: ok (bit-exact)"
port=$("$work/venv/bin/python" -c 'import socket; s=socket.socket(); s.bind(("127.0.0.1", 0)); print(s.getsockname()[1])')
"$teleop" serve --port "$port" > "$work/serve.log" 2>&1 &
serve_pid=$!
status() {  # the HTTP status of GET URL (000: no answer), without curl, which a fresh machine may lack
    "$work/venv/bin/python" -c 'import sys, urllib.request, urllib.error
try:
    print(urllib.request.urlopen(sys.argv[1], timeout=5).status)
except urllib.error.HTTPError as e:
    print(e.code)
except OSError:
    print("000")' "$1"
}
for _ in $(seq 1 120); do
    code=$(status "http://127.0.0.1:$port/")
    [ "$code" = 200 ] && break
    kill -0 "$serve_pid" 2>/dev/null || fail "teleop serve exited: $(tail -3 "$work/serve.log")"
    sleep 0.5
done
for page in / /phone; do
    code=$(status "http://127.0.0.1:$port$page")
    [ "$code" = 200 ] || fail "teleop serve: GET $page answered $code: $(tail -3 "$work/serve.log")"
done
say "teleop serve: / and /phone answer 200"
kill -INT "$serve_pid"  # as Ctrl-C
rc=0; wait "$serve_pid" || rc=$?
serve_pid=""
[ "$rc" = 0 ] || fail "teleop serve exited with $rc on Ctrl-C: $(tail -3 "$work/serve.log")"
say "teleop serve: stopped by Ctrl-C (exit 0)"
# The LeRobot plugin distribution (plugins/lerobot_robot_mujoco_teleop, issue 58) builds and installs beside the wheel
# (--no-deps: LeRobot is the lerobot extra's, not the core's), and its import, which LeRobot runs at every command's
# start, needs nothing more than the core and loads no MuJoCo, torch or viser.
"$python" -m pip wheel --no-deps --no-build-isolation -q "$work/src/plugins/lerobot_robot_mujoco_teleop" -w "$work/plugin" \
    || fail "pip wheel could not build plugins/lerobot_robot_mujoco_teleop"
"$work/venv/bin/python" -m pip install -q --no-deps "$work"/plugin/lerobot_robot_mujoco_teleop-*.whl \
    || fail "pip install of the plugin's wheel failed"
"$work/venv/bin/python" -c 'import sys, lerobot_robot_mujoco_teleop
heavy = [m for m in ("mujoco", "torch", "viser") if m in sys.modules]
sys.exit(f"it imported {heavy}" if heavy else 0)' || fail "importing lerobot_robot_mujoco_teleop from the wheel failed"
say "the LeRobot plugin distribution: installed, imports light"
