#!/usr/bin/env bash
# A normal install works: build the wheel (not editable), install it into a fresh venv and use it from
# outside the checkout: `teleop scenes`, a scripted `teleop run` that records, `teleop replay --verify`
# (bit-exact), and `teleop serve` answering / and /phone with HTTP 200.
#   .ci/wheel_check.sh [PYTHON]   (default: the test venv's python, for its pip cache and interpreter)
set -euo pipefail
root=$(cd "$(dirname "$0")/.." && pwd)
python=${1:-$root/.venv/bin/python}
work=$(mktemp -d)
serve_pid=""
cleanup() { [ -n "$serve_pid" ] && kill "$serve_pid" 2>/dev/null; rm -rf "$work"; }
trap cleanup EXIT
say() { echo "wheel check: $*" >&2; }
# From a clean copy: setuptools' build/ folder in the checkout could hold files of an earlier build.
mkdir "$work/src"
(cd "$root" && git ls-files -co --exclude-standard | while read -r f; do [ -f "$f" ] && printf '%s\0' "$f"; done) \
    | (cd "$root" && xargs -0 cp --parents -t "$work/src")
"$python" -m pip wheel --no-deps -q "$work/src" -w "$work/dist"
wheel=$(ls "$work"/dist/mujoco_teleop-*.whl)
say "built $(basename "$wheel")"
"$python" -m venv "$work/venv"
"$work/venv/bin/python" -m pip install -q "$wheel"
say "installed it (not editable) into a fresh venv"
teleop="$work/venv/bin/teleop"
site=$("$work/venv/bin/python" -c 'import scenes, pathlib; print(pathlib.Path(scenes.__file__).parent)')
cd "$work"  # outside the checkout: only the installed package can be found
export MUJOCO_GL=${MUJOCO_GL:-egl}
scenes=$("$teleop" scenes)
grep -q '^lift' <<< "$scenes" || { say "teleop scenes does not list lift: $scenes"; exit 1; }
say "teleop scenes: ok"
"$teleop" run --device "script:$site/scripts/lift_pick.json" --scene lift --record "$work/eps" --json > "$work/run.json"
grep -q '"success": true' "$work/run.json" || { say "the scripted run did not succeed: $(cat "$work/run.json")"; exit 1; }
"$teleop" replay "$work/eps/episode_000000.mcap" --verify --json > "$work/verify.json"
say "teleop run + replay --verify (bit-exact): ok"
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
    kill -0 "$serve_pid" 2>/dev/null || { say "teleop serve exited: $(tail -3 "$work/serve.log")"; exit 1; }
    sleep 0.5
done
for page in / /phone; do
    code=$(status "http://127.0.0.1:$port$page")
    [ "$code" = 200 ] || { say "GET $page answered $code"; exit 1; }
done
say "teleop serve: / and /phone answer 200"
