#!/usr/bin/env bash
# Make benchmarks/.venv-brian2, a virtualenv with Brian2 for bench_encoder.py (never committed: .gitignore has
# benchmarks/.venv*/). It sees the system site-packages and installs Brian2 (+ Cython, sympy) on top, with its own
# numpy < 2.4: Brian2 2.9 still wraps numpy.ndarray.ptp, which numpy 2.4 (rigctl's) removed, so Brian2 needs an
# older numpy than rigctl, and gets it inside the venv only.
set -euo pipefail
here="$(cd "$(dirname "$0")" && pwd)"
venv="$here/.venv-brian2"
py="${PYTHON:-python3}"
if [ ! -x "$venv/bin/python" ]; then
    "$py" -m venv --system-site-packages "$venv"
fi
"$venv/bin/python" -m pip install -q "brian2>=2.7" "numpy<2.4"
"$venv/bin/python" -c "import brian2, numpy; print('brian2', brian2.__version__, 'numpy', numpy.__version__)"
