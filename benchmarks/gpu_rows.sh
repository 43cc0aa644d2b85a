#!/usr/bin/env bash
# The benchmarks' GPU rows in one run: bench_sim.py, bench_sim3d.py, bench_filters.py and
# bench_se3_rbpf.py with --device cuda, each guarded (a failure prints its traceback in its log
# and the next one still runs) and bounded in time (a SIGINT past its budget: the traceback
# says where it was).
#
#     bash benchmarks/gpu_rows.sh OUT_DIR [--quick]
#
# Writes OUT_DIR/<benchmark>.log and OUT_DIR/<benchmark>.json (8 files) and prints the
# tables. The full run takes about 5 minutes on an H100; --quick (tiny sizes) about 1.
# DEVICE=cpu runs the same script on the CPU (a check of the script itself; with --quick the
# CPU's small default sizes). MuJoCo, torch-kf and FilterPy are optional: their rows are left
# out where they are not installed (MuJoCo is a CPU reference, left out on a GPU anyway).
set -u
out=${1:?usage: gpu_rows.sh OUT_DIR [--quick]}
quick=${2:-}
device=${DEVICE:-cuda}
here=$(cd "$(dirname "$0")" && pwd)
mkdir -p "$out"
export PYTHONUNBUFFERED=1

python3 - "$device" "$here" <<'EOF'
import platform, sys
sys.path.insert(0, sys.argv[2])
import torch
from _timing import device_name
device = torch.device(sys.argv[1])
print(f"torch {torch.__version__}, Python {platform.python_version()}, {device}: "
      f"{device_name(device)}, {torch.get_num_threads()} threads")
EOF

# run NAME SECONDS ARGS...: one benchmark, its output appended to OUT_DIR/NAME.log, its JSON in
# OUT_DIR/NAME.json, SIGINT after SECONDS (then SIGKILL 15 s later); fails if the benchmark did.
run() {
    local name=$1 seconds=$2
    shift 2
    local start=$SECONDS
    echo "== $name $*" | tee -a "$out/$name.log"
    timeout -s INT -k 15 "$seconds" python3 "$here/$name.py" --device "$device" \
        --out "$out/$name.json" "$@" >>"$out/$name.log" 2>&1
    local status=$?
    if [ "$status" -ne 0 ]; then
        echo "FAILED: $name (exit $status after $((SECONDS - start)) s), the log's tail:"
        tail -n 25 "$out/$name.log"
        return 1
    fi
    echo "done: $name in $((SECONDS - start)) s"
    # the tables and the summary lines
    grep -E '^\||^(Planar|Spatial|MuJoCo|Target|Targets|CPU|filter|torch rows|target)' \
        "$out/$name.log" | cut -c1-200
}

# (a function, so that bash has read the whole script before it starts the first benchmark)
main() {
    if [ "$quick" = "--quick" ]; then
        # if compiling the simulator fails or overruns, the eager rows alone
        run bench_sim 200 --quick || run bench_sim 60 --quick --eager
        run bench_sim3d 60 --quick
        run bench_filters 90 --quick --kernels eager --particles 1000 --rounds 2
        run bench_se3_rbpf 120 --quick
    else
        run bench_sim 200 --steps 50 || run bench_sim 90 --steps 50 --eager
        run bench_sim3d 75 --steps 50
        run bench_filters 110 --kernels eager --particles 1000,10000,100000 --rounds 5
        run bench_se3_rbpf 150 --eager --modes 4,all --particles 1000,10000 --steps 20
    fi
    echo "== results in $out"
}

main
