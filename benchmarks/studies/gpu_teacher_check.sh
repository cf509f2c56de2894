#!/usr/bin/env bash
# Frozen study (issue 30, point 5), as of commit 722e080; figures: BENCHMARKS.md, "The torch backend on a GPU
# (point 5)". Its successor: `python3 -m benchmarks.gpu_run --steps teacher`.
# The teacher's two ICP backends on the GPU machine (python3 -m benchmarks.teacher_backends: icp.backend=cpu
# against icp.backend=torch on CUDA, 32 synthetic test pairs), about 6 minutes in all. That machine reaches no registry:
# the packages the teacher imports beyond its image (hdbscan with scikit-learn, joblib, threadpoolctl, cloudpickle,
# narwhals; hydra-core with omegaconf, antlr4-python3-runtime, which icpflow.teacher.config imports; pypatchworkpp)
# come from .wheels/ (cp312 wheels, not in git: carry the folder). The project is not installed: PYTHONPATH holds
# the repository root.
#
#     bash benchmarks/studies/gpu_teacher_check.sh [teacher_backends.py arguments, after the defaults]
#
# Writes $OUT/backends.json and $OUT/backends.log (OUT defaults to outputs/teacher_backends). numba compiles the
# teacher's kernels on the first run in a checkout (about a minute, said on stderr); the warm-up calls come after.
set -uo pipefail
cd "$(dirname "$0")/../.."
OUT=${OUT:-outputs/teacher_backends}
PY=${PYTHON:-python3}
mkdir -p "$OUT"
export PYTHONPATH="$PWD${PYTHONPATH:+:$PYTHONPATH}" PYTHONUNBUFFERED=1

# Installed into python3's environment, resolved against what it holds (a package already there stays); if that
# fails, every wheel whose distribution is missing goes to /tmp/site without dependencies.
if ! "$PY" -m pip install -q --no-index --no-cache-dir --find-links .wheels hdbscan hydra-core pypatchworkpp; then
    echo "gpu_teacher_check: resolved install failed; the missing wheels without dependencies into /tmp/site"
    missing=()
    for wheel in .wheels/*.whl; do
        "$PY" -m pip show -q "$(basename "$wheel" | cut -d- -f1)" >/dev/null 2>&1 || missing+=("$wheel")
    done
    if [ ${#missing[@]} -gt 0 ]; then
        "$PY" -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --target /tmp/site "${missing[@]}" \
            || exit 1
        export PYTHONPATH="$PYTHONPATH:/tmp/site"
    fi
fi
"$PY" -c "import hdbscan._hdbscan_boruvka, hydra.core.config_store, pypatchworkpp, yaml" || exit 1

# --max-seconds: no pair starts after 200 s of timed calls (the tables then cover the pairs done); timeout: the hard
# stop, after which backends.log still holds a line per call
timeout 330 "$PY" -m benchmarks.teacher_backends --pairs 32 --max-seconds 200 --json "$OUT/backends.json" "$@" \
    2>&1 | tee "$OUT/backends.log"
