#!/usr/bin/env bash
# Set up dp5k: system packages, a virtual environment in .venv, PyTorch 2.13.0 and the project. Idempotent: re-running
# is cheap. `make setup` / `make demo` run it as is (what the demo needs); `make test` adds --with-tests (pytest and
# its plugins, the peer libraries, umockdev and socat for the capture peer tests).
#
# Environment (or make variables: `make setup TORCH_INDEX_URL=...`):
#   PYTHON           the interpreter for .venv (default: the first of python3.11, 3.12, 3.13, 3.14, python3 that is >= 3.11)
#   TORCH_SPEC       what pip installs for PyTorch (default torch==2.13.0)
#   TORCH_INDEX_URL  where pip takes it from, e.g. https://download.pytorch.org/whl/cu128 for a CUDA build. Default: the
#                    CPU build: a torch wheel pip's own configuration already offers locally (find-links), else
#                    https://download.pytorch.org/whl/cpu. Changing it later reinstalls torch.
# Every problem is one line starting "setup:" that says what to do; apt's own errors are shown as they come.
set -euo pipefail
cd "$(dirname "$0")/.."

with_tests=0
for arg in "$@"; do
  case "$arg" in
    --with-tests) with_tests=1 ;;
    *) echo "setup: unknown option $arg (known: --with-tests)" >&2; exit 2 ;;
  esac
done
die() { echo "setup: $*" >&2; exit 1; }
is_root() { [ "$(id -u)" -eq 0 ]; }

# --- system packages (Debian/Ubuntu: installed as root, else named with the command to run) ---------------------
# libusb-1.0-0: pyusb's backend and `import open3d`; libgomp1: OpenMP of torch and open3d; umockdev + socat: the
# capture peer tests (--with-tests only).
missing_debs() { local p; for p in "$@"; do dpkg-query -W -f='${Status}' "$p" 2>/dev/null | grep -q "ok installed" || echo "$p"; done; }
get_debs() {  # get_debs required|optional WHAT PACKAGE...: apt-get install as root, else one line naming the command
  local need=$1 what=$2 msg; shift 2
  if is_root; then
    echo "setup: installing $what: $*"
    if apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq --no-install-recommends "$@"; then
      return 0
    fi
    msg="apt-get could not install $* (its errors are above)"
  else
    msg="missing $what $*; install them, then run this again: sudo apt-get install -y $*"
  fi
  if [ "$need" = required ]; then die "$msg"; fi
  echo "setup: $msg" >&2
}
if command -v dpkg-query >/dev/null && command -v apt-get >/dev/null; then
  mapfile -t need < <(missing_debs libusb-1.0-0 libgomp1)
  [ ${#need[@]} -eq 0 ] || get_debs required "system packages" "${need[@]}"
  if [ "$with_tests" -eq 1 ]; then
    mapfile -t need < <(missing_debs umockdev socat)
    [ ${#need[@]} -eq 0 ] || get_debs optional "test tools (the capture peer tests skip without them)" "${need[@]}"
  fi
else
  echo "setup: no apt-get here; make sure libusb-1.0 and libgomp (OpenMP) are installed$([ "$with_tests" -eq 1 ] && echo ", and umockdev and socat for the capture peer tests")" >&2
fi

# --- Python >= 3.11 with its venv module ---------------------------------------------------------------------------
py_version() { "$1" -c 'import sys; print("%d.%d" % sys.version_info[:2])' 2>/dev/null; }
new_enough() { "$1" -c 'import sys; sys.exit(sys.version_info < (3, 11))' 2>/dev/null; }
if [ -n "${PYTHON:-}" ]; then
  command -v "$PYTHON" >/dev/null || die "PYTHON=$PYTHON is not a command; name a Python 3.11 or newer"
  new_enough "$PYTHON" || die "PYTHON=$PYTHON is Python $(py_version "$PYTHON"); dp5k needs 3.11 or newer"
  PY=$PYTHON
else
  PY=""
  for cand in python3.11 python3.12 python3.13 python3.14 python3; do
    if command -v "$cand" >/dev/null && new_enough "$cand"; then PY=$cand; break; fi
  done
  if [ -z "$PY" ]; then
    found=$(command -v python3 >/dev/null && echo " (python3 is $(py_version python3))" || true)
    die "dp5k needs Python 3.11 or newer and found none$found; install it (Debian/Ubuntu: sudo apt-get install python3.11 python3.11-venv) or name one: PYTHON=/path/to/python3.11"
  fi
fi
pyver=$(py_version "$PY")

venv_ok() { [ -x .venv/bin/python ] && new_enough .venv/bin/python && .venv/bin/python -m pip --version >/dev/null 2>&1; }
if ! venv_ok; then
  # Debian and Ubuntu ship venv (its ensurepip) apart from python3.X itself
  if ! "$PY" -c 'import venv, ensurepip' 2>/dev/null; then
    if is_root && command -v apt-get >/dev/null; then
      get_debs required "the venv module of Python $pyver" "python$pyver-venv"
    else
      die "Python $pyver has no venv module; install it: sudo apt-get install python$pyver-venv"
    fi
  fi
  [ -e .venv ] && echo "setup: .venv is unusable (an older Python, or half made); making it again" && rm -rf .venv
  echo "setup: creating .venv (Python $pyver)"
  if ! "$PY" -m venv .venv; then
    rm -rf .venv  # never leave a half-made .venv that a later run would take as ready
    die "Python $pyver could not create .venv (see above); on Debian/Ubuntu: sudo apt-get install python$pyver-venv"
  fi
fi
. .venv/bin/activate

# --- PyTorch (CPU by default) and dp5k -------------------------------------------------------------------------------
TORCH_SPEC=${TORCH_SPEC:-torch==2.13.0}
torch_source() {  # the pip arguments that choose the torch build
  if [ -n "${TORCH_INDEX_URL:-}" ]; then
    echo "--index-url $TORCH_INDEX_URL"
  elif python -m pip install --dry-run --no-deps --no-index -q "$TORCH_SPEC" >/dev/null 2>&1; then
    echo ""  # pip's configuration offers a local wheel (find-links): as pip resolves it, offline
  else
    echo "--index-url https://download.pytorch.org/whl/cpu"
  fi
}
stamp=.venv/.dp5k-installed
test_stamp=.venv/.dp5k-tests-installed
want_torch="$TORCH_SPEC ${TORCH_INDEX_URL:-default}"
had_torch=$(cat "$stamp" 2>/dev/null || true)
[ -f "$stamp" ] && [ -z "$had_torch" ] && had_torch="torch==2.13.0 default"  # a stamp of the setup before the choice
if [ ! -f "$stamp" ] || [ pyproject.toml -nt "$stamp" ] || [ "$had_torch" != "$want_torch" ]; then
  python -m pip install -q --upgrade pip
  src=$(torch_source)
  echo "setup: installing $TORCH_SPEC ${src:-from the local wheel pip is configured with}"
  # torch first, pinned, from the chosen index: an unpinned torch from PyPI would pull several GB of CUDA wheels
  reinstall=$([ -f "$stamp" ] && [ "$had_torch" != "$want_torch" ] && echo "--force-reinstall" || true)
  # shellcheck disable=SC2086  # $src and $reinstall are zero or more words
  python -m pip install -q $reinstall $src "$TORCH_SPEC"
  python -m pip install -q -e .
  echo "$want_torch" > "$stamp"
  rm -f "$test_stamp"
fi
if [ "$with_tests" -eq 1 ] && { [ ! -f "$test_stamp" ] || [ pyproject.toml -nt "$test_stamp" ]; }; then
  echo "setup: installing the test tools (dev and peers extras)"
  python -m pip install -q -e ".[dev,peers]"
  touch "$test_stamp"
fi
echo "setup: ready ($(python -c 'import torch, cv2; print("torch", torch.__version__, "opencv", cv2.__version__)'))"
