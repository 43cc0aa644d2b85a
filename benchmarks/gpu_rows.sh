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

python3 - "$device" <<'EOF'
import platform, sys, torch
device = torch.device(sys.argv[1])
name = torch.cuda.get_device_name(device) if device.type == "cuda" else platform.processor()
print(f"torch {torch.__version__}, Python {platform.python_version()}, {device}: {name}")
EOF

# run NAME SECONDS ARGS...: one benchmark, its output in OUT_DIR/NAME.log, its JSON in
# OUT_DIR/NAME.json, SIGINT after SECONDS (then SIGKILL 15 s later).
run() {
    local name=$1 seconds=$2
    shift 2
    local start=$SECONDS
    echo "== $name $*"
    timeout -s INT -k 15 "$seconds" python3 "$here/$name.py" --device "$device" \
        --out "$out/$name.json" "$@" >"$out/$name.log" 2>&1
    local status=$?
    if [ "$status" -ne 0 ]; then
        echo "FAILED: $name (exit $status after $((SECONDS - start)) s), the log's tail:"
        tail -n 25 "$out/$name.log"
    else
        echo "done: $name in $((SECONDS - start)) s"
        # the tables and the summary lines
        grep -E '^\||^(Planar|Spatial|MuJoCo|Target|Targets|CPU|filter|torch rows|target)' \
            "$out/$name.log" | cut -c1-200
    fi
}

if [ "$quick" = "--quick" ]; then
    run bench_sim 150 --quick
    run bench_sim3d 60 --quick
    run bench_filters 90 --quick --kernels eager --particles 1000 --rounds 2
    run bench_se3_rbpf 120 --quick
else
    run bench_sim 150 --steps 50
    run bench_sim3d 75 --steps 50
    run bench_filters 90 --kernels eager --particles 1000,10000,100000 --rounds 5
    run bench_se3_rbpf 120 --eager --modes 4,all --particles 1000,10000 --steps 30
fi
echo "== results in $out"
