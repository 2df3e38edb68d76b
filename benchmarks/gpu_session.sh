#!/usr/bin/env bash
# The GPU figures of README ("GPU") in one prepared run, for a session that is lent a GPU
# machine for a few minutes: the same `affinebody run` as benchmarks/run_scale.py at 10^5 and
# 10^6 bodies, and the parts of a step at 10^6 (benchmarks/step_phases.py).
#
#   benchmarks/gpu_session.sh fetch [REV]  # here, once: the wheels the GPU image lacks, into
#                                          # .whl/ (and REV's src/ into .whl/rev/src)
#   benchmarks/gpu_session.sh run          # there (carry .whl): prints and writes $OUT/*.txt
#
# With a REV (the commit before a change of the GPU path), `run` also times the forces of
# REV's source tree in a process of their own on the same GPU: an A/B of the change within
# the one run a session may get.
#
# The workplace's CUDA image (Python 3.12) has JAX with CUDA, h5py, numba, matplotlib, rich and
# click, not pydantic: `fetch` downloads pydantic and its three dependencies at the versions of
# this checkout's .venv into .whl/ (ignored through .git/info/exclude). `run` installs them
# under /tmp/site and runs the project from src/ (no pip install: the image's JAX may be newer
# than pyproject's pin, and its CUDA build is the one to measure). About 3 minutes on an H200
# after the machine's start (2026-11-27, before the first command and the XLA A/B of
# run_scale below were added; about two more minutes expected for them).
set -uo pipefail
cd "$(dirname "$0")/.."

case "${1:-}" in
fetch)
    grep -qx "/.whl/" .git/info/exclude 2>/dev/null || echo "/.whl/" >> .git/info/exclude
    versions=$(.venv/bin/python - <<'EOF'
from importlib.metadata import version
print(" ".join(f"{name}=={version(name)}" for name in
               ("pydantic", "pydantic-core", "annotated-types", "typing-inspection")))
EOF
    ) || exit 1
    # shellcheck disable=SC2086
    python3 -m pip download -q --no-deps --only-binary=:all: --python-version 3.12 \
        --implementation cp --platform manylinux_2_28_x86_64 --platform manylinux_2_17_x86_64 \
        --platform manylinux2014_x86_64 -d .whl $versions && ls .whl
    rm -rf .whl/rev
    if [ -n "${2:-}" ]; then
        mkdir -p .whl/rev && git archive "$2" src | tar -x -C .whl/rev && git rev-parse "$2" \
            > .whl/rev/commit && echo "src/ of $(cat .whl/rev/commit) in .whl/rev"
    fi
    ;;
run)
    OUT=${OUT:-/tmp/gpu_session}
    mkdir -p "$OUT"
    if ls .whl/*.whl > /dev/null 2>&1; then
        python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade \
            --target /tmp/site .whl/*.whl || exit 1
        export PYTHONPATH=/tmp/site
    fi
    export PYTHONPATH="$PWD/src${PYTHONPATH:+:$PYTHONPATH}" PYTHONUNBUFFERED=1
    { nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv,noheader
      python3 -c "import jax; print('jax', jax.__version__, jax.devices())"; } 2>&1 \
        | tee "$OUT/device.txt"
    # first the A/B of the JAX pair kernel's two programs (Triton, the default on a GPU, and
    # XLA) with their forces compared, and the parts of a pass of the Triton program: a
    # failing Triton compile shows here, in a minute
    python3 benchmarks/step_phases.py --bodies 1000000 --loop-steps 0 --pair-program xla \
        --f-in-xla --no-padding-skip --triton-blocks 128 512 --pair-parts 2>&1 \
        | tee "$OUT/programs_1e6.txt"
    if [ -d .whl/rev/src ]; then  # the same forces from the source tree of `fetch REV`
        echo "source tree of $(cat .whl/rev/commit):" | tee "$OUT/rev_1e6.txt"
        PYTHONPATH="$PWD/.whl/rev/src:${PYTHONPATH#*:}" python3 benchmarks/step_phases.py \
            --bodies 1000000 --loop-steps 0 2>&1 | tee -a "$OUT/rev_1e6.txt"
    fi
    python3 benchmarks/run_scale.py --bodies 1000000 --steps 200 2>&1 | tee "$OUT/scale_1e6.txt"
    # the parts of a step, and (--profile) the kernels the GPU ran per step of the loop
    python3 benchmarks/step_phases.py --bodies 1000000 --profile 2>&1 | tee "$OUT/phases_1e6.txt"
    python3 benchmarks/run_scale.py --bodies 100000 --steps 1000 2>&1 | tee "$OUT/scale_1e5.txt"
    # the same command with the XLA program of the pair forces: the whole-command A/B
    AFFINEBODY_PAIR_PROGRAM=xla python3 benchmarks/run_scale.py --bodies 1000000 --steps 200 \
        2>&1 | tee "$OUT/scale_1e6_xla.txt"
    ;;
*)
    echo "usage: benchmarks/gpu_session.sh fetch|run" >&2
    exit 2
    ;;
esac
