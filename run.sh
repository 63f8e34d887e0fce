#!/usr/bin/env bash
# One script for the two jobs on a fresh machine; each makes its own virtual environment.
#   ./run.sh [FLAGS]    the browser teleop session (Panda, lift), recording into ./episodes; FLAGS go to `teleop serve`
#   ./run.sh test       installs everything (LeRobot, browser, X server) and runs the whole test suite
#   ./run.sh ARGS...    any other `teleop` command, e.g. ./run.sh run --device script:scenes/scripts/lift_pick.json
set -euo pipefail
cd "$(dirname "$0")"
VENV=${TELEOP_VENV:-.venv}

find_python() {
    local candidates=(python3.12 python3.13 python3)
    for exe in "${candidates[@]}"; do
        if command -v "$exe" >/dev/null 2>&1 && "$exe" -c 'import sys; sys.exit(sys.version_info < (3, 12))' 2>/dev/null; then
            command -v "$exe"; return 0
        fi
    done
    for exe in "$HOME"/.pyenv/versions/3.12*/bin/python3.12 /usr/local/bin/python3.12 /opt/python*/bin/python3.12; do
        if [ -x "$exe" ]; then echo "$exe"; return 0; fi
    done
    return 1
}

make_venv() {  # make_venv EXTRAS
    local extras=$1 stamp
    if [ ! -x "$VENV/bin/python" ]; then
        local py
        py=$(find_python) || { echo "run.sh: Python 3.12 or newer is needed (LeRobot 0.6 requires it); install python3.12 and try again" >&2; exit 2; }
        "$py" -m venv "$VENV"
        "$VENV/bin/python" -m pip install -q --upgrade pip
    fi
    stamp="$VENV/.installed-$(cat pyproject.toml | sha1sum | cut -c1-12)-$extras"
    if [ ! -f "$stamp" ]; then
        echo "run.sh: installing the project into $VENV (${extras:-core})..." >&2
        if [ -n "$extras" ]; then
            "$VENV/bin/python" -m pip install -q -e ".[$extras]"
        else
            "$VENV/bin/python" -m pip install -q -e .
        fi
        touch "$stamp"
    fi
}

debian_test_packages() {
    # Xvfb + xdotool (keyboard tests), Chromium (browser tests), Mesa (offscreen rendering), ffmpeg libs for video.
    local need=()
    command -v Xvfb >/dev/null || need+=(xvfb)
    command -v xdotool >/dev/null || need+=(xdotool)
    [ -x /usr/bin/chromium ] || need+=(chromium)
    ldconfig -p | grep -q libOSMesa || need+=(libosmesa6)
    ldconfig -p | grep -q 'libEGL.so.1' || need+=(libegl1)
    [ -e /usr/lib/x86_64-linux-gnu/dri ] || [ -e /usr/lib/aarch64-linux-gnu/dri ] || need+=(libgl1-mesa-dri)
    if [ ${#need[@]} -gt 0 ]; then
        if [ "$(id -u)" = 0 ]; then
            echo "run.sh: installing Debian packages: ${need[*]}" >&2
            apt-get update -qq
            DEBIAN_FRONTEND=noninteractive apt-get install -y -qq "${need[@]}" >/dev/null
        else
            echo "run.sh: the tests need these Debian packages: sudo apt-get install ${need[*]}" >&2
            exit 2
        fi
    fi
}

robomimic_for_tests() {
    # tests/test_robomimic.py opens our HDF5 files with robomimic's own SequenceDataset. Installed
    # without its dependencies (tensorboard, matplotlib, egl_probe...: for its training and rendering):
    # its loader needs torch, h5py and numpy, which the lerobot extra brings, and these three.
    if ! "$VENV/bin/python" -c 'import importlib.metadata as m, sys; [m.version(d) for d in ("termcolor", "tensorboardX", "tqdm")]; sys.exit(m.version("robomimic") != "0.3.0")' 2>/dev/null; then
        echo "run.sh: installing robomimic 0.3.0 (without its dependencies) into $VENV..." >&2
        "$VENV/bin/python" -m pip install -q termcolor tensorboardX tqdm
        "$VENV/bin/python" -m pip install -q --no-deps robomimic==0.3.0
    fi
}

first=${1:-serve}
case "$first" in -*) first=serve; set -- serve "$@" ;; esac
case "$first" in
    test)
        shift || true
        debian_test_packages
        make_venv "test,lerobot,train,cluster"
        robomimic_for_tests
        export MUJOCO_GL=${MUJOCO_GL:-egl} HF_HUB_OFFLINE=1 PYTHONUNBUFFERED=1
        checks=0  # CI: the linter and a normal (non-editable) install before the tests; the tests run either way
        set +e
        if [ -n "${TELEOP_CI_CHECKS:-}" ]; then
            "$VENV/bin/ruff" check . || { echo "run.sh: ruff check found problems (above)" >&2; checks=1; }
            bash .ci/wheel_check.sh "$VENV/bin/python" || { echo "run.sh: the wheel check failed (above)" >&2; checks=1; }
        fi
        "$VENV/bin/python" -m pytest "$@"
        rc=$?
        set -e
        if [ "$rc" = 5 ]; then echo "run.sh: pytest collected no tests: that is a failure" >&2; exit 1; fi
        if [ "$rc" = 0 ] && [ "$checks" != 0 ]; then echo "run.sh: the tests passed but a CI check failed" >&2; exit 1; fi
        exit "$rc"
        ;;
    serve)
        shift || true
        make_venv ""
        exec "$VENV/bin/teleop" serve --record episodes "$@"
        ;;
    *)
        make_venv ""
        exec "$VENV/bin/teleop" "$@"
        ;;
esac
