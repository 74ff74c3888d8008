#!/usr/bin/env bash
# The GPU-session checklist of docs/benchmarks.md as one command, for a lent GPU machine with a short lease.
#
#   bash benchmarks/gpu_session.sh OUT_DIR [ITEMS]
#
# Runs the checklist's items in the order of what they decide (correctness first; the cold time to accuracy first
# after the machine starts, since it measures a cold start), each in a fresh process under its own time limit, so
# that one item that hangs or fails leaves the others' results. Writes OUT_DIR/NAME.log per item, the sample
# runs' reports, and OUT_DIR/session.tgz with those and the files the items wrote under benchmarks/results. ITEMS: a
# comma-separated subset of
# cold,tta,checks,overhead,overhead_base,split,sample,step,coarse,profile,profile_nosources,tta_envelope,suite_multislice,suite_envelope,reg_demo
# (default: all, in that order). The limits are about twice what each took on an H200 (2026-11-26). A 15-minute lease holds one call of
# about 9 minutes with the machine's start, then a short second call at once on the warm machine (it is given back
# 30 s after a call): on an H100 (2026-11-26) tta,checks,sample,step,profile,suite_multislice took 425 s, and
# reg_demo with REG_DEMO_SETTINGS=auto about 110 s (27 s of it simulating the demo).
# GPU_SESSION_BUDGET_S (seconds, optional): the items share this budget: each item's limit is cut to what is left of
# it (less 20 s for the archive), and an item with under 20 s left is skipped, so that the archive is always written
# inside the device call's own limit. REG_DEMO_SETTINGS (default auto,0,50): the weights reg_demo runs.
# split reads the suite's scenes from out/scenes (carry them, or make-scenes first).
# The package runs from src/ (PYTHONPATH), so a machine with torch, numpy, scikit-image, tifffile and pydantic needs
# no install.
set -u
out=${1:?usage: gpu_session.sh OUT_DIR [ITEMS]}
items=${2:-cold,tta,checks,overhead,overhead_base,split,sample,step,coarse,profile,profile_nosources,tta_envelope,suite_multislice,suite_envelope,reg_demo}
mkdir -p "$out"
tmp=$(mktemp -d)
touch "$tmp/start"
export PYTHONPATH="$PWD/src:$PWD${PYTHONPATH:+:$PYTHONPATH}" PYTHONUNBUFFERED=1
py=${PYTHON:-python3}

item() {  # item NAME LIMIT_S COMMAND...: run one item in a fresh process, its output in OUT/NAME.log
    local name=$1 limit=$2
    shift 2
    case ",$items," in *",$name,"*) ;; *) return 0 ;; esac
    local t0=$SECONDS
    if [ "${GPU_SESSION_BUDGET_S:-0}" -gt 0 ]; then
        local left=$((GPU_SESSION_BUDGET_S - SECONDS - 20))
        if [ "$left" -lt 20 ]; then echo "== $name skipped: ${left} s of the budget left"; return 0; fi
        [ "$left" -lt "$limit" ] && limit=$left
    fi
    echo "== $name (limit ${limit} s): $*"
    timeout -k 5 "$limit" "$@" >"$out/$name.log" 2>&1
    local rc=$?
    echo "   rc $rc after $((SECONDS - t0)) s; last lines:"
    tail -n 6 "$out/$name.log" | sed 's/^/   | /'
}

{
    nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv,noheader
    "$py" -c "import torch, sys; print(sys.version.split()[0], torch.__version__, torch.cuda.get_device_name(0))"
} 2>&1 | tee "$out/device.txt"

item cold 90 "$py" -m benchmarks run cold_start --device cuda --repeats 2   # fresh processes: first on a fresh machine
item tta 90 "$py" -m benchmarks run time_to_accuracy --device cuda
item checks 240 "$py" -m benchmarks run gpu_checks
# the finest iteration against its model step (issue 48); BASE_SRC (a `git archive REV src` unpacked) times that code too
item overhead 90 "$py" -m benchmarks run iteration_overhead --device cuda --rounds 3 --iterations 30
[ -n "${BASE_SRC:-}" ] && PYTHONPATH="$BASE_SRC:$PYTHONPATH" item overhead_base 90 "$py" -m benchmarks run iteration_overhead --device cuda --rounds 3 --iterations 30
item split 45 "$py" -m benchmarks run split_field --device cuda --write
# the README's command on the GPU, with the field window the defaults choose and with the split window
sample='for w in auto split; do "$0" -c "import sys; from napari_fdt.cli import main; sys.exit(main())" reconstruct sample_data/letters --device "$2" --quiet \
    --overwrite --truth sample_data/letters/ground_truth_ri.tif --field-window $w --out "$1/sample_$w.tif" || exit; done'
item sample 75 bash -c "$sample" "$py" "$tmp" "${SAMPLE_DEVICE:-cuda}"
item step 60 "$py" -m benchmarks run step_speed --device cuda
item coarse 60 "$py" -m benchmarks run coarse_stage_speed --device cuda --cuda-graph --repeats 10
item profile 120 "$py" -m benchmarks run profile_step --solver-demo --no-modes
# the same solver profile without the sources' calibration (its whitened step waits for the GPU twice per iteration)
item profile_nosources 90 "$py" -m benchmarks run profile_step --solver-only --solver-set '{"calibrate_sources": false}'
item tta_envelope 90 "$py" -m benchmarks run time_to_accuracy --device cuda --coarse-model envelope
item suite_multislice 150 "$py" -m benchmarks run suite --device cuda --scenes demo,sample \
    --out benchmarks/results/suite_cuda_multislice.json
item suite_envelope 150 "$py" -m benchmarks run suite --device cuda --scenes demo,sample --coarse-model envelope \
    --out benchmarks/results/suite_cuda_envelope.json
# issue 12's target, the demo with the defaults (checklist item 7): simulates the demo scene, then three runs
item reg_demo 480 "$py" -m benchmarks run regularisation run --scenes demo --settings "${REG_DEMO_SETTINGS:-auto,0,50}" --device cuda

cp "$tmp"/sample_*.json "$out"/ 2>/dev/null
# one archive (a lease's file transfer may take few files): the logs, the sample reports, what went to benchmarks/results
tar czf "$out/session.tgz" -C "$out" $(cd "$out" && ls | grep -v "^session.tgz$") $(find benchmarks/results -newer "$tmp/start" -type f | sed "s|^|-C $PWD |")
echo "== done after $SECONDS s"
