#!/usr/bin/env bash
# The GPU checks in one prepared run, on a machine with an NVIDIA GPU and ctpipe's dependencies:
#   1. every GPU kernel against its CPU twin (python -m ctpipe.gpu.check, two sizes);
#   2. benchmarks/bench_gpu.py: forward projection and FDK against diffct on the same card, the
#      analytic projector, all against ctpipe's CPU kernels;
#   3. the default `ctpipe validate` on the GPU twice (cold: kernels compiled; warm), then on the
#      CPU: the timings, and whether the two devices give the same angles.
# Results go to $OUT (default /tmp/ctpipe-gpu). Wheels in .whl/ (numpy < 2.5 for numba-cuda,
# olefile, diffct) are installed first when present, for a machine with no network; on the
# device tool's image (Python 3.12, numba-cuda 0.30.4, numpy 2.5, torch) they were fetched with
#   pip download --no-deps --only-binary=:all: --python-version 3.12 --implementation cp \
#       --platform manylinux_2_28_x86_64 --platform manylinux_2_17_x86_64 -d .whl \
#       numpy==2.4.6 olefile diffct==2.5.0
# (17 MB; .whl/ ignored by git, carried with the run). The whole script took 589 s on an H100.
# STAGES picks what runs (default all): check, bench, validate, profile (a warm validate on the
# GPU under cProfile, its 40 costliest functions printed); SIZES and KERNELS the bench's sizes
# and kernels, CHECK_SIZES the check's.
#
#     bash benchmarks/gpu_machine.sh
#     STAGES="check bench profile" SIZES="512 1024" bash benchmarks/gpu_machine.sh
set -u
now() { date +%s%N; }
seconds() { echo $(( ($(now) - $1) / 1000000 ))e-3; }
OUT=${OUT:-/tmp/ctpipe-gpu}
mkdir -p "$OUT"
export PYTHONUNBUFFERED=1
if [ -d .whl ]; then
    python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site .whl/*.whl \
        || exit 1
    export PYTHONPATH=/tmp/site:$PWD
else
    export PYTHONPATH=$PWD
fi
{
    nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv,noheader
    python3 -c "import numpy, numba, numba_cuda; from numba import cuda; print('numpy', numpy.__version__, 'numba', numba.__version__, 'numba-cuda', getattr(numba_cuda, '__version__', '?'), 'cuda', cuda.is_available())"
    nproc
} 2>&1 | tee "$OUT/machine.txt"

STAGES=${STAGES:-check bench validate}
SIZES=${SIZES:-256 512 1024}
has() { case " $STAGES " in *" $1 "*) return 0;; esac; return 1; }

if has check; then
echo "== kernels against the CPU"
for size in ${CHECK_SIZES:-8 40}; do
    start=$(now)
    python3 -m ctpipe.gpu.check $size
    echo "check $size: exit $?, $(seconds $start) s"
done

fi

if has bench; then
echo "== benchmark"
# shellcheck disable=SC2086
python3 benchmarks/bench_gpu.py --sizes $SIZES --repeats 3 --cpu-up-to "${CPU_UP_TO:-512}" --phases \
    --kernels ${KERNELS:-forward fdk analytic} 2>&1 \
    | tee "$OUT/bench_gpu.txt"
fi

if has profile; then
echo "== default validate on the GPU, cold, then warm under cProfile"
for run in cold warm; do
    start=$(now)
    if [ $run = cold ]; then
        python3 -m ctpipe.cli --device cuda validate --out /tmp/validate-profile --json > "$OUT/validate-cold.json"
    else
        python3 -m cProfile -o "$OUT/validate.prof" -m ctpipe.cli --device cuda validate --out /tmp/validate-profile \
            --json > "$OUT/validate-warm.json"
    fi
    echo "validate cuda $run: exit $?, wall $(seconds $start) s"
    python3 -c "import json, sys; r = json.load(open(sys.argv[1])); print(json.dumps({k: r.get(k) for k in ('timings_s', 'angle_errors')}, default=str)[:800])" "$OUT/validate-$run.json"
done
python3 -c "import pstats; s = pstats.Stats('$OUT/validate.prof'); s.sort_stats('cumulative').print_stats(40); s.sort_stats('tottime').print_stats(30)" \
    2>&1 | cut -c1-160 > "$OUT/validate-profile.txt"
head -c 6000 "$OUT/validate-profile.txt"
fi

if has validate; then
echo "== default validate"
for run in cuda-cold cuda-warm cpu; do
    device=${run%%-*}
    start=$(now)
    python3 -m ctpipe.cli --device "$device" validate --out "/tmp/validate-$run" --json > "/tmp/validate-$run.json"
    status=$?
    wall=$(seconds $start)
    echo "validate $run: exit $status, wall $wall s"
    python3 - "$run" "$wall" <<'EOF'
import json, sys
run, wall = sys.argv[1], sys.argv[2]
report = json.load(open(f"/tmp/validate-{run}.json"))
keep = {key: report.get(key) for key in ("timings_s", "angle_errors", "verdict")}
print(run, wall, json.dumps(keep, default=str)[:1500])
EOF
    cp "/tmp/validate-$run.json" "$OUT/validate-$run.json"
done
cp /tmp/validate-cuda-warm/angles.csv "$OUT/angles-cuda.csv"
cp /tmp/validate-cpu/angles.csv "$OUT/angles-cpu.csv"
python3 - <<'EOF'
import numpy as np
gpu = np.genfromtxt("/tmp/validate-cuda-warm/angles.csv", delimiter=",", names=True)
cpu = np.genfromtxt("/tmp/validate-cpu/angles.csv", delimiter=",", names=True)
diff = gpu["estimated_relative_deg"] - cpu["estimated_relative_deg"]
print(f"GPU - CPU estimated angles: max |diff| {np.max(np.abs(diff)):.6f} deg, RMS {np.sqrt(np.mean(diff**2)):.6f} deg")
for name, table in (("gpu", gpu), ("cpu", cpu)):
    print(name, "RMS error", float(np.sqrt(np.mean(table["estimated_error_deg"] ** 2))))
EOF
fi
