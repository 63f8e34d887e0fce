#!/usr/bin/env bash
# One script for the two jobs on a fresh machine; each makes its own virtual environment.
#   ./run.sh [FLAGS]    the browser teleop session (Panda, lift), recording into ./episodes; FLAGS go to `teleop serve`
#   ./run.sh test       installs everything (LeRobot, browser, X server) and runs the whole test suite
#   ./run.sh ARGS...    any other `teleop` command, e.g. ./run.sh run --device script:scenes/scripts/lift_pick.json
# Each installs only what the venv ($TELEOP_VENV, default .venv) lacks; pip's output goes to $VENV/install.log,
# shown only when an install fails.
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

# The install stamp: $VENV/.installed-<pyproject hash>-<extras, comma list>. pip installs add up, so the
# venv holds every extra of every stamp with this pyproject's hash; a request for a subset needs no install.
has_extras() {  # has_extras HASH EXTRAS: 0 when the stamps of HASH together hold every extra asked for
    local hash=$1 want=$2 have="" stamp extra
    for stamp in "$VENV"/.installed-"$hash"-*; do
        [ -f "$stamp" ] || continue
        have="$have,${stamp##*/.installed-"$hash"-},"
    done
    [ -n "$have" ] || return 1
    for extra in ${want//,/ }; do
        case "$have" in *",$extra,"*) ;; *) return 1 ;; esac
    done
    return 0
}

quiet_install() {  # quiet_install ARGS...: pip into $VENV, its output kept in $VENV/install.log and shown only on failure
    local log="$VENV/install.log"
    if ! "$VENV/bin/python" -m pip "$@" >>"$log" 2>&1; then
        echo "run.sh: pip install into $VENV failed; the end of $log:" >&2
        tail -n 60 "$log" >&2
        exit 1
    fi
}

make_venv() {  # make_venv EXTRAS
    local extras=$1 hash
    if [ ! -x "$VENV/bin/python" ]; then
        local py
        py=$(find_python) || { echo "run.sh: Python 3.12 or newer is needed (LeRobot 0.6 requires it); install python3.12 and try again" >&2; exit 2; }
        "$py" -m venv "$VENV"
        quiet_install install --upgrade pip
    fi
    hash=$(sha1sum <pyproject.toml | cut -c1-12)
    if ! has_extras "$hash" "$extras"; then
        echo "run.sh: installing the project into $VENV (${extras:-core}; pip's output in $VENV/install.log)..." >&2
        if [ -n "$extras" ]; then
            quiet_install install -e ".[$extras]"
        else
            quiet_install install -e .
        fi
        touch "$VENV/.installed-$hash-$extras"
    fi
}

debian_test_packages() {
    # Xvfb + xdotool (keyboard tests), Chromium (browser tests), Mesa (offscreen rendering), ffmpeg libs for video.
    local need=()
    command -v Xvfb >/dev/null || need+=(xvfb)
    command -v xdotool >/dev/null || need+=(xdotool)
    [ -x /usr/bin/chromium ] || need+=(chromium)
    command -v npm >/dev/null || need+=(npm)  # fetches IWER, the WebXR emulator of the XR page's tests
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

iwer_for_tests() {
    # tests/test_xr_*.py emulate a Quest 3 in headless Chromium with Meta's IWER (npm `iwer`, MIT): fetched from the
    # npm registry into a cache, only when missing, never into the repository (tests/test_xr_*.py and bench/xr.py find it there).
    local dir="${TELEOP_IWER_CACHE:-$HOME/.cache/mujoco-teleop/iwer}/2.5.0"
    if [ ! -f "$dir/package/build/iwer.min.js" ]; then
        echo "run.sh: fetching iwer 2.5.0 (the WebXR emulator) into $dir..." >&2
        mkdir -p "$dir"
        (cd "$dir" && npm pack iwer@2.5.0 --silent >/dev/null && tar xzf iwer-2.5.0.tgz && rm -f iwer-2.5.0.tgz) \
            || { echo "run.sh: could not fetch iwer 2.5.0 with npm (the XR page's tests need it)" >&2; exit 1; }
    fi
}

lerobot_plugin_for_tests() {
    # LeRobot's commands find this project's robot, teleoperator and env types through the thin distribution
    # plugins/lerobot_robot_mujoco_teleop (issue 58; docs/lerobot_commands.md): installed after the project, when missing.
    if ! "$VENV/bin/python" -c 'import importlib.metadata as m; m.version("lerobot_robot_mujoco_teleop")' 2>/dev/null; then
        echo "run.sh: installing the LeRobot plugin (plugins/lerobot_robot_mujoco_teleop) into $VENV..." >&2
        quiet_install install --no-build-isolation ./plugins/lerobot_robot_mujoco_teleop
        rm -rf plugins/lerobot_robot_mujoco_teleop/build
    fi
}

robomimic_for_tests() {
    # tests/test_robomimic.py opens our HDF5 files with robomimic's own SequenceDataset. Installed
    # without its dependencies (tensorboard, matplotlib, egl_probe...: for its training and rendering):
    # its loader needs torch, h5py and numpy, which the lerobot extra brings, and these three.
    if ! "$VENV/bin/python" -c 'import importlib.metadata as m, sys; [m.version(d) for d in ("termcolor", "tensorboardX", "tqdm")]; sys.exit(m.version("robomimic") != "0.3.0")' 2>/dev/null; then
        echo "run.sh: installing robomimic 0.3.0 (without its dependencies) into $VENV..." >&2
        quiet_install install termcolor tensorboardX tqdm
        quiet_install install --no-deps robomimic==0.3.0
    fi
}

first=${1:-serve}
case "$first" in -*) first=serve; set -- serve "$@" ;; esac
case "$first" in
    test)
        shift || true
        debian_test_packages
        make_venv "test,lerobot,train,cluster,hardware"
        robomimic_for_tests
        lerobot_plugin_for_tests
        iwer_for_tests
        export MUJOCO_GL=${MUJOCO_GL:-egl} HF_HUB_OFFLINE=1 PYTHONUNBUFFERED=1
        # One OpenMP/MKL thread per process: three workers share the 2 cores, and torch's intra-op threads only
        # spin against each other there (bench/train_eval.sh sets the same for its training and evaluation)
        export OMP_NUM_THREADS=${OMP_NUM_THREADS:-1} MKL_NUM_THREADS=${MKL_NUM_THREADS:-1}
        checks=0  # CI: the linter and a normal (non-editable) install before the tests; the tests run either way
        set +e
        if [ -n "${TELEOP_CI_CHECKS:-}" ]; then
            "$VENV/bin/ruff" check . || { echo "run.sh: ruff check found problems (above)" >&2; checks=1; }
            bash .ci/wheel_check.sh "$VENV/bin/python" || { echo "run.sh: the wheel check failed (above)" >&2; checks=1; }
        fi
        # On pytest-xdist workers (tests/conftest.py keeps them apart: ports from the OS, their own folders and Ray);
        # TELEOP_TEST_WORKERS=0 runs in one process. loadgroup keeps the tests that share a file's module-scoped
        # fixture (a served page, a dataset) on one worker; the rest go to whichever worker is free, in the order
        # tests/suite_time.py gives them (unit tests first).
        "$VENV/bin/python" -m pytest -n "${TELEOP_TEST_WORKERS:-3}" --dist loadgroup --no-loadscope-reorder "$@"
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
