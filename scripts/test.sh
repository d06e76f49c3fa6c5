#!/usr/bin/env bash
# Install everything the tests need on a fresh Debian machine, build the firmware, and run the whole test suite.
# This is the README's test command; .ci/run calls it. Extra arguments go to pytest.
set -euo pipefail
cd "$(dirname "$0")/.."

# the run stays at the priority it was started with. (It raised itself to nice -10 where allowed, to keep wall-paced
# simulated boards ahead of other programs; a simulated rig's boards and host now share one clock, and a starved host
# pauses its world instead. Above nice 0 the suite starved the kernel's own workers, which hand a pty's bytes from
# writer to reader: beside two CPU hogs, requests and answers of the simulated boards sat up to seconds in the kernel
# and the conformance tests' answer timeouts ran out, three loaded runs in a row: rigctl.simulation.priority.)

DEBIAN_PACKAGES=(
  # AVR toolchain, Arduino core and the AVR simulator (firmware build and hardware-in-the-loop tests)
  gcc-avr avr-libc binutils-avr arduino-core-avr simavr libsimavr-dev libsimavrparts1 libelf-dev pkg-config make g++
  # the host C compiler that builds the drum controller's controller.c for the model rig (rigctl.simulation.mega_c)
  gcc
  # independent Modbus master for tests
  mbpoll
  # the drum controller's C under cppcheck's MISRA C:2012 addon (tests/firmware/test_fw_misra.py)
  cppcheck
  # virtual screen and the libraries Qt needs to run offscreen / under Xvfb
  xvfb xauth libegl1 libgl1 libxkbcommon0 libxkbcommon-x11-0 libdbus-1-3 libfontconfig1 libxcb-cursor0 libxcb-icccm4 libxcb-keysyms1
  # a window manager and real X input for the GUI tests under Xvfb (tests/gui/test_gui_x11.py)
  openbox xdotool
)

SUDO=""
if [ "$(id -u)" != 0 ]; then SUDO="sudo"; fi

# the cores other programs keep busy (a shared CI machine, CPU hogs beside the run), sampled over 1 s from /proc/stat
# before anything of ours starts: the test workers are counted on the cores left (see the pytest step below)
others_busy_cores="$(python3 -c '
import os, time
def snap():
    with open("/proc/stat") as f:
        v = [int(x) for x in f.readline().split()[1:]]
    return sum(v), v[3] + v[4]
t0, i0 = snap(); time.sleep(1.0); t1, i1 = snap()
print(int(round((1 - (i1 - i0) / max(t1 - t0, 1)) * (os.cpu_count() or 1))))' 2>/dev/null || echo 0)"

# everything the checks make goes to a scratch folder outside the checkout, removed at the end: the firmware build
# (rigctl.firmware honours $RIGCTL_FIRMWARE_BUILD; the firmware tests use this build), the drum controller's C logic
# built for the host (rigctl.simulation.mega_c honours $RIGCTL_HOST_BUILD; the model rig loads it), import-linter's cache,
# Hypothesis' example database, numba's compiled kernels, Python's byte code, pytest's cache, the apt log
TEST_TMP="$(mktemp -d "${TMPDIR:-/tmp}/rigctl-test.XXXXXX")"
trap 'rm -rf "$TEST_TMP"' EXIT

# the Debian packages install in the background, beside the Python install, the numba kernels and the byte code (none
# of which needs them: measured on a fresh machine, apt took ~15-20 s of mostly waiting on downloads and dpkg, one after
# the other with the rest); waited for before the firmware build, the first step that needs them
missing=()
for p in "${DEBIAN_PACKAGES[@]}"; do
  dpkg-query -W -f='${Status}' "$p" 2>/dev/null | grep -q "install ok installed" || missing+=("$p")
done
apt_pid=""
apt_install() {  # apt_install PACKAGE...: one apt-get update and install, quiet; its output in $TEST_TMP/apt.log
  { $SUDO apt-get update -qq && DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq --no-install-recommends "$@"
  } >> "$TEST_TMP/apt.log" 2>&1
}
wait_apt() {  # wait for the background apt-get (if any); its log and a failure if it failed
  if [ -n "$apt_pid" ]; then
    local rc=0
    wait "$apt_pid" || rc=$?
    apt_pid=""
    if [ "$rc" != 0 ]; then
      tail -n 20 "$TEST_TMP/apt.log"
      echo "apt-get install ${missing[*]} failed (exit $rc)"
      exit "$rc"
    fi
  fi
}
if [ ${#missing[@]} -gt 0 ]; then
  echo "== apt-get install ${missing[*]} (in the background)"
  apt_install "${missing[@]}" &
  apt_pid=$!
fi

# a virtual environment of its own (Debian 12 refuses pip outside one, PEP 668), unless one is active already. Made
# without pip when the interpreter that makes it has a pip of its own, which then installs uv into it: ensurepip's
# fresh pip compiled itself from source at every start (venv with pip and uv from it: 6.1 s, 5.2 CPU-s; without pip
# and uv from the outer pip: 3.2 s, 2.7 CPU-s); uv then installs pip too (the tests use the environment's pip)
if [ -z "${VIRTUAL_ENV:-}" ]; then
  VENV="${RIGCTL_VENV:-.venv}"
  if [ ! -x "$VENV/bin/python3" ]; then
    if python3 -m pip --version >/dev/null 2>&1 && python3 -m venv --without-pip "$VENV" 2>/dev/null \
        && python3 -m pip --python "$VENV/bin/python3" install -q --disable-pip-version-check uv 2>/dev/null; then
      echo "== python3 -m venv --without-pip $VENV, uv into it"
    else
      rm -rf "$VENV"
      echo "== python3 -m venv $VENV"
      if ! python3 -m venv "$VENV" 2>/dev/null; then  # Debian's python3 needs python3-venv for ensurepip
        rm -rf "$VENV"
        wait_apt  # (one apt-get at a time: dpkg's lock)
        apt_install python3-venv || { tail -n 20 "$TEST_TMP/apt.log"; exit 1; }
        python3 -m venv "$VENV"
      fi
    fi
  fi
  # shellcheck disable=SC1091
  . "$VENV/bin/activate"
fi

# uv (PyPI's installer from Astral) resolves and installs the same requirements as pip, in parallel and without
# compiling byte code: on a fresh 2-core machine pip took ~47 s here; pip itself if uv cannot be had or fails (into an
# environment without pip: ensurepip's first)
echo "== install -e .[test] and pip with uv, pip if that fails (into $VIRTUAL_ENV)"
if ! { { python3 -m uv --version >/dev/null 2>&1 || python3 -m pip install -q --disable-pip-version-check uv; } \
       && python3 -m uv pip install -q -e ".[test]" pip; }; then
  echo "== uv failed: pip install -e .[test]"
  python3 -m pip --version >/dev/null 2>&1 || python3 -m ensurepip -q
  python3 -m pip install -q --disable-pip-version-check -e ".[test]"
fi

# the build tools a guide's `pip install` of a plugin takes into its isolated build environment (docs/guides/
# my-hardware.md: as a user's pip fetches them from the index), downloaded once so that the tests build offline
# (tests/guides.py guide_env: PIP_NO_INDEX with this folder as PIP_FIND_LINKS)
if python3 -m pip download -q --disable-pip-version-check --only-binary :all: -d "$TEST_TMP/wheelhouse" \
    "setuptools>=70.1" wheel > "$TEST_TMP/wheelhouse.log" 2>&1; then
  export RIGCTL_TEST_WHEELHOUSE="$TEST_TMP/wheelhouse"
else
  echo "== pip download of the guides' build tools failed (the my-hardware guide's test fails): $(tail -n 1 "$TEST_TMP/wheelhouse.log")"
fi

export RIGCTL_FIRMWARE_BUILD="$TEST_TMP/firmware" RIGCTL_HOST_BUILD="$TEST_TMP/host" HYPOTHESIS_STORAGE_DIRECTORY="$TEST_TMP/hypothesis" \
  NUMBA_CACHE_DIR="$TEST_TMP/numba"

# byte code, in a tree of its own under the scratch folder (PYTHONPYCACHEPREFIX), never beside the sources in the
# checkout or the venv: a machine whose environment says PYTHONDONTWRITEBYTECODE=1 (this one does), with the packages
# installed by uv (which compiles none), has every process of the suite compile every module it imports from source,
# again and again (measured: importing scikit-learn, scipy, h5py, numba, pymodbus and the trial runner took 4.3 CPU-s
# without byte code, 1.6 with; the suite starts hundreds of processes: CLI subprocesses, the GUI's analysis processes,
# test workers)
export PYTHONPYCACHEPREFIX="$TEST_TMP/pycache"
unset PYTHONDONTWRITEBYTECODE

t0=$(date +%s)
phase() { echo "== [$(( $(date +%s) - t0 )) s] $*"; }

export QT_QPA_PLATFORM=offscreen
# BLAS (OpenBLAS, numpy's and scipy's) on one thread in every process of the run: the test workers keep every core busy
# already, and a BLAS call's second thread then spins waiting on the first (measured: tests/analysis at -n 2 used 28.9 /
# 27.8 CPU-s with OpenBLAS's default threads, 25.0 / 23.4 with one; the paper guide's `analyze --table1` 6.3 -> 5.5).
# No test judges BLAS's threading; the results are the same
export OPENBLAS_NUM_THREADS=1
# what the checkout looks like before the checks (untracked and ignored files too, but byte code): no check may
# change it
checkout_state() { git status --porcelain --ignored 2>/dev/null | grep -v '__pycache__/$' || true; }
before="$(checkout_state)"

# numba's kernels compiled once into the cache before the tests start, in two processes side by side while ruff runs and
# the firmware builds (scripts/compile_kernels.py: ~14 + ~8 s of CPU since no kernel has a parallel build);
# otherwise each test worker, GUI analysis process and CLI subprocess that starts before the cache is ready compiles the
# ones it needs. (Tried: the parallel part beside the first tests, at nice 5 and at nice 19, with the tests that may
# encode waiting for it. pytest took as long (260 s against 244-260 with 6 workers; 242 s against 219-231 with 7), and
# rigs starting beside the compile missed their first answers: a ready banner not within 3 s, a Modbus read not answered
# in three tries.)
kernel_pids=()
for part in serial parallel; do
  python3 scripts/compile_kernels.py "$part" > "$TEST_TMP/compile_kernels_$part.log" 2>&1 &
  kernel_pids+=($!)
done

# the byte code of everything the test modules import, written once into the byte-code tree by one collection (as
# the workers collect: same interpreter, same test modules), beside the kernels: the pytest-xdist workers all collect
# the whole suite at the same moment, and on a cold tree each compiled the same modules from source (measured, one
# process: 10.4 CPU-s to collect on a cold tree, 3.9 on a warm one; six workers); then that of the analysis stack,
# which the test modules import inside the tests that use it (a collection that needs none of it: ~2.5 CPU-s less in
# each worker), but which most workers load some time in the run (an in-process `rigctl analyze`, the GUI's job
# server): importing it cold took 7.7 CPU-s, warm 2.3, and two workers starting together would each compile it
python3 -m pytest --collect-only -q -p no:cacheprovider > "$TEST_TMP/collect.log" 2>&1 \
  && python3 -c 'import rigctl.analysis.tasks, rigctl.analysis.model, rigctl.analysis.report, rigctl.analysis.stats
import rigctl.encoding.estimators, sklearn.utils.estimator_checks, scipy.signal, scipy.ndimage, scipy.io' \
  >> "$TEST_TMP/collect.log" 2>&1 &
collect_pid=$!

phase "ruff check (rules and per-file ignores in pyproject.toml)"
python3 -m ruff check --no-cache .

# the import contracts (lint-imports; the layers in pyproject.toml, docs/architecture.md) and mypy (settings in
# pyproject.toml), one after the other, in the background at a lower priority (nice 10; ~3 + ~10 s of CPU): the CPU is
# busy until the workers have collected, and partly idle later, while the long tests wait on rigs paced to the wall
# clock; their verdicts are printed and checked after pytest. The lint-imports command is run by this interpreter
# (import-linter has no `python -m` entry point). In a session of their own (setsid): Linux weighs each session as one
# scheduling group, and in this script's session, beside two CPU hogs started with it, nice 10 left them a twentieth of
# a group's share: a loaded run waited 113 s for mypy after its tests had passed (its own group takes a fair share)
phase "import contracts (lint-imports) and mypy, in the background (nice 10, a session of their own)"
own_session=()
if command -v setsid >/dev/null 2>&1; then own_session=(setsid -w); fi
"${own_session[@]}" nice -n 10 bash -c '
    python3 -c "import sys; from importlinter.cli import lint_imports_command; sys.exit(lint_imports_command())" \
      --cache-dir "$1/import-linter" > "$1/lint-imports.log" 2>&1; echo $? > "$1/lint-imports.status"
    python3 -m mypy --cache-dir /dev/null > "$1/mypy.log" 2>&1; echo $? > "$1/mypy.status"' _ "$TEST_TMP" &
static_pid=$!

phase "Debian packages (waiting for apt-get)"
wait_apt

phase "build firmware (into $RIGCTL_FIRMWARE_BUILD)"
# as the tests build it (rigctl.firmware.build: the sources' BUILD_ID, under the build folder's lock): a plain make
# leaves the id out, and the first test's build would then relink the images while other workers read them
python3 -c 'from rigctl import firmware; firmware.build()'

# the drum controller's controller.c for the host (the model rig's controller: rigctl.simulation.mega_c), once, before
# the workers start: each would otherwise wait under the build folder's lock for the first one's build
phase "build the drum controller's C logic for the host (into $RIGCTL_HOST_BUILD)"
python3 -c 'from rigctl.simulation import mega_c; mega_c.build()'

phase "numba kernels and byte code (waiting for scripts/compile_kernels.py and the collection)"
for pid in "${kernel_pids[@]}"; do
  # (a failed compile here is only slower tests: each kernel then compiles on first use, and the tests say why)
  wait "$pid" || echo "compiling the numba kernels beforehand failed:"
done
cat "$TEST_TMP"/compile_kernels_*.log
# (a failed collection shows again, with its reason, when pytest collects)
wait "$collect_pid" || echo "collecting the tests beforehand (byte code) failed: $(tail -n 1 "$TEST_TMP/collect.log")"

phase "pytest"
# three workers a core and one more, at most 8 (pytest-xdist; RIGCTL_TEST_WORKERS overrides): the suite waits on rigs
# paced to the wall clock, and one worker a core left about half of the CPU idle (clean clone, 2 cores, nothing else
# running: 680 s of pytest at load ~1.2 with 2 workers, 449 s at load ~3.7 with 4, CPU then ~80 % busy). Once the
# processes stopped compiling byte code and kernels of their own, 4 workers left the CPU 40-70 % busy for minutes (377 s
# of pytest); 5 gave 353 s; once the simulated rigs cost half as much CPU, 5 left it 46-90 % busy for ~100 s mid-run and
# 6 gave 307 s. With 6, the CPU was still 41-75 % busy for ~100 s mid-run (all six in tests waiting on wall clocks); 7
# gave 231 s of pytest against 244-260 with 6. An earlier try at 4 failed three timing
# tests at load 8-10 (another session's work beside it), a try at 8 four (drum clients on simulated boards with the
# hardware's 0.5 s answer timeout, among them); those wait for their real events, or use the rig kind's timeout, now. A
# test module stays on one worker (--dist loadfile: module-scoped rigs and windows), or its xdist_group parts do; the
# longest units first (tests/conftest.py)
# On a machine other programs keep busy (measured at the start: $others_busy_cores cores), the workers are counted on
# the cores left, at least one: every worker beside a CPU hog adds one more runnable process to share the cores with,
# and the rigs paced to the wall clock then starve (a run beside two hogs on 2 cores with 7 workers failed 25 timing
# tests in its first third; each simulated board is a thread that must run every millisecond or so)
cores="$(nproc 2>/dev/null || echo 1)"
# (Linux weighs each session as one group, so programs of another session keep their share whatever our nice level)
free_cores=$(( cores - others_busy_cores < 1 ? 1 : cores - others_busy_cores ))
workers="${RIGCTL_TEST_WORKERS:-$(( free_cores * 3 + 1 > 8 ? 8 : free_cores * 3 + 1 ))}"
echo "== $workers test workers ($cores cores, $others_busy_cores kept busy by other programs at the start; nice $(nice))"
status=0
export RIGCTL_FAILURES_LOG="$TEST_TMP/failures.log"  # failed tests and their tier (tests/conftest.py)
export RIGCTL_RERUNS_LOG="$TEST_TMP/reruns.log"  # each attempt run again at once, and why it failed (printed below)
# A wall-clock test that fails in the parallel run is first run again at once, on its own worker, while the others go
# on (pytest-rerunfailures; RIGCTL_WALL_RERUNS, tests/conftest.py): most such failures were the saturated CPU's, and
# pass then, without adding their wall time to the run's end (a serial rerun of one firmware test took ~25 s of the
# run's ~330). The log lists each as RERUN (-r R); one that fails twice gets its rerun alone below
RIGCTL_WALL_RERUNS=1 python3 -m pytest -q -n "$workers" --dist loadfile --durations=25 --strict-markers -r fER \
  -o cache_dir="$TEST_TMP/pytest-cache" "$@" || status=$?
phase "pytest done (exit $status)"
if [ -s "$RIGCTL_RERUNS_LOG" ]; then
  echo "== run again at once in the parallel run (node id, phase, where and why the first attempt failed):"
  sed 's/^/   /' "$RIGCTL_RERUNS_LOG"
fi
# Wall-clock failures (failed twice in the parallel run) get one more chance, alone. The parallel run keeps the CPU
# saturated (~1,000 CPU-s of tests on a 2-core machine, workers beside the rigs they pace), and a test of a wall-clock
# tier (realtime, gui: tests/conftest.py WALL_CLOCK_TIERS; the simulated rigs' tests, firmware and conformance among
# them, share one clock with their host and get no second run: docs/architecture.md) can then fail for want of CPU: each run
# failed a different handful of 3-7 of ~1,190 (a 0.73 s STOP against 0.5, a simulated board's banner not within 3 s, a
# frame burst stamped late). Once the parallel run is over, those (at most 25) run again one at a time, with the CPU to
# themselves; the run fails if any fails again, and on any failure of a logic test (those judge simulated time and
# never get a second chance). Every rerun is listed in the log: a test that keeps needing one is a test to fix.
if [ "$status" = 1 ] && [ -s "$RIGCTL_FAILURES_LOG" ] \
    && awk -F'\t' '$2 != "wall" { logic = 1 } END { exit logic }' "$RIGCTL_FAILURES_LOG"; then
  mapfile -t rerun < <(cut -f1 "$RIGCTL_FAILURES_LOG" | sort -u)
  if [ "${#rerun[@]}" -le 25 ]; then
    phase "rerunning ${#rerun[@]} wall-clock failure(s) alone, one at a time:"
    printf '   %s\n' "${rerun[@]}"
    mv "$RIGCTL_FAILURES_LOG" "$TEST_TMP/failures-parallel.log"
    status=0
    python3 -m pytest -q --strict-markers -o cache_dir="$TEST_TMP/pytest-cache" "$@" "${rerun[@]}" \
      || status=$?
    phase "rerun done (exit $status)"
  else
    echo "== ${#rerun[@]} wall-clock failures: not rerun (more than 25 is not the load)"
  fi
fi
static_status=0
wait "$static_pid" || true
for check in lint-imports mypy; do
  echo "== $check:"
  cat "$TEST_TMP/$check.log"
  rc="$(cat "$TEST_TMP/$check.status" 2>/dev/null || echo 1)"
  if [ "$rc" != 0 ]; then echo "$check failed (exit $rc)"; static_status=1; fi
done
after="$(checkout_state)"
if [ "$before" != "$after" ]; then
  echo "the checks changed the checkout (git status --porcelain --ignored, before -> after):"
  diff <(echo "$before") <(echo "$after") || true
  exit 1
fi
phase "done"
if [ "$static_status" != 0 ]; then exit "$static_status"; fi
exit "$status"
