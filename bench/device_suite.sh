#!/usr/bin/env bash
# GPU benchmark suite, one stage per device call (each stage fits in 10 minutes on one H100/H200).
#   bash bench/device_suite.sh tests|sim|peers|peers64|spec|slices|dataset|dataset-sweep|dataset-learnable|dataset-scale|dataset-full|scale-probe|profile-dataset|profile-tshirt|learn|reports|accuracy|self-contact|profile-self-contact  OUTDIR
# Writes STAGE.log (everything printed) and STAGE.jsonl (the benches' JSON lines) to OUTDIR.
set -uo pipefail
stage=$1; out=${2:-/tmp/suite}; mkdir -p "$out"
export PYTHONUNBUFFERED=1 TQDM_DISABLE=1
log="$out/$stage.log"; jl="$out/$stage.jsonl"
run() { echo "+ $*" >>"$log"; timeout "${T:-400}" "$@" >>"$log" 2>&1; echo "rc=$?" >>"$log"; }
# the shipped spec NAME written to FILE with the audit off (its Newton solves are CPU work)
spec_without_audit() {
  python - "$1" "$2" <<'PY'
import sys, yaml
from pipelines.spec import load_spec
spec = load_spec(sys.argv[1])
spec["audit"]["samples"] = 0
yaml.safe_dump(spec, open(sys.argv[2], "w"))
PY
}
case $stage in
  tests)
    T=420 run python -m pytest -q -p no:cacheprovider tests/test_cloth_oracles.py tests/test_cloth_builder.py \
      tests/test_solver_worlds.py tests/test_contact_collider.py tests/test_contact_self.py tests/test_quality.py \
      tests/test_learn_common.py tests/test_tailornet_model.py tests/test_body_anny.py tests/test_body_kinematics.py \
      tests/test_sequence.py ;;
  sim)
    T=200 run python bench/bench_sim_throughput.py --device cuda:0 --worlds 1 4 16 64 128 256 512 --frames 20 --out "$jl"
    T=150 run python bench/bench_sim_throughput.py --device cuda:0 --worlds 64 --relax --max-frames 400 --out "$jl"
    T=220 run python bench/bench_sim_error_vs_time.py --device cuda:0 --plot "$out/error_vs_time.png" --out "$jl" ;;
  peers)
    # 1 world, every solver, substeps x iterations sweep; Newton's error checkpointed every 25 frames
    T=${T:-540} run python bench/bench_sim_newton.py --device cuda:0 --out "$jl" ;;
  peers64)
    # 64 worlds (references from 1 world), then where a frame's GPU time goes (kernel profile)
    T=360 run python bench/bench_sim_newton.py --device cuda:0 --worlds 64 --solvers ours_xpbd_gs ours_xpbd_gs_jb newton_vbd \
      --substeps 5 10 --iterations 10 --out "$jl"
    T=120 run python bench/bench_sim_throughput.py --device cuda:0 --worlds 1 64 --frames 10 --profile --out "$jl"
    T=120 run python bench/bench_sim_throughput.py --device cuda:0 --scene tshirt --resolution 7700 --worlds 240 \
      --frames 10 --profile --out "$jl" ;;
  profile-tshirt)
    # the dataset batch's stepping alone, by kernel: 256 t-shirts (7.7k) in 40 rest shapes, body queries on every
    # 5th substep as in the spec; then each world reading its own copy of the element data (the sharing's A/B)
    for share in "" --no-share-element-data; do
      T=150 run python bench/bench_sim_throughput.py --device cuda:0 --scene tshirt --resolution 7700 --worlds 256 \
        --garments 40 --contact-detect-every 5 --frames 20 --profile $share --out "$jl"
    done ;;
  spec)
    # one shipped spec whole (SPEC=tailornet-pants, ...), audit off (its Newton solves are CPU work):
    # the heartbeat lines and the closing summary go to the log; rerun the same stage to resume
    spec_without_audit "${SPEC:?SPEC=name of a shipped spec}" "$out/$SPEC.yaml"
    T=${T:-540} run python -m pipelines.cli generate-dataset "$out/$SPEC.yaml" --out "/tmp/ds-$SPEC" --no-progress
    du -sh "/tmp/ds-$SPEC/shards" >>"$log" 2>&1 ;;
  slices)
    # kept share and cost of each spec in SPECS on a slice (POSES train / 2 test poses per pair, audit off):
    # the spec's XPBD, then VBD 10 x 3 (the stepping that meets the hanging-strip bar)
    for name in ${SPECS:-tailornet-pants tailornet-skirt tailornet-shirt}; do
      spec_without_audit "$name" "$out/$name.yaml"
      T=${T:-240} run python bench/bench_dataset.py --spec "$out/$name.yaml" --poses ${POSES:-4} --test-poses 2 \
        --device cuda:0 --out "/tmp/slice-$name-xpbd"
      T=${T:-240} run python bench/bench_dataset.py --spec "$out/$name.yaml" --poses ${POSES:-4} --test-poses 2 \
        --device cuda:0 --out "/tmp/slice-$name-vbd" --sim solver=vbd --sim substeps=10 --sim iterations=3
    done ;;
  dataset)
    T=540 run python bench/bench_dataset.py --spec tailornet-tshirt --poses ${POSES:-40} --test-poses 10 --device cuda:0 \
      --keep --out /tmp/tn ;;
  dataset-sweep)
    # keep rate and frames per target against tolerance / pose range, short slices
    for cfg in "--sim tolerance=0.01" "--sim tolerance=0.05" "--sim tolerance=0.05 --range-scale 0.6"; do
      T=${T:-150} run python bench/bench_dataset.py --spec tailornet-tshirt --poses ${POSES:-8} --test-poses 4 \
        --device cuda:0 --out /tmp/tn-sweep $cfg
    done ;;
  dataset-learnable)
    # a slice with relaxed filters (self-intersections, distortion) so the learners get frames;
    # kept in /tmp/tn for the learn stage
    T=${T:-300} run python bench/bench_dataset.py --spec tailornet-tshirt --poses ${POSES:-12} --test-poses 6 \
      --device cuda:0 --keep --out /tmp/tn --sim tolerance=0.05 ${RANGE:+--range-scale $RANGE} \
      --filter max_self_intersections=${MAX_SI:-60} --filter max_distorted_fraction=0.01 ;;
  profile-dataset)
    T=${T:-150} run python -m cProfile -s tottime bench/bench_dataset.py --spec tailornet-tshirt --poses 3 --test-poses 2 \
      --device cuda:0 --out /tmp/tn-prof --sim tolerance=0.05 ;;
  learn)
    # DATA=/tmp/tn-scale trains on a kept dataset-scale run (KEEP=1) of the same warm machine; the paper's
    # epochs per stage (LF 100, HF 800, g 400, baseline 100) unless EPOCHS sets one count for all
    T=${T_TRAIN:-400} run python -m pipelines.cli train tailornet --data ${DATA:-/tmp/tn} --out /tmp/tn-run --device cuda ${EPOCHS:+--epochs $EPOCHS} --no-progress
    T=${T_EVAL:-90} run python -m pipelines.cli evaluate /tmp/tn-run --data ${DATA:-/tmp/tn} --device cuda --out "$out/eval" ;;
  scale-probe)
    # where the full-width run's time goes: the t-shirt's raw stepping cost at the pipeline's widths, then
    # 4 minutes of the full-width slice (heartbeats split stepping / bodies / recording; the bench prints a
    # partial JSON line when timeout stops it)
    T=150 run python bench/bench_sim_throughput.py --device cuda:0 --scene tshirt --resolution 7700 --worlds 64 128 240 \
      --frames 20 --out "$jl"
    T=${T:-240} run python bench/bench_dataset.py --spec tailornet-tshirt --poses 240 --test-poses 30 \
      --sim poses_per_task=30 --device cuda:0 --out /tmp/tn-scale ;;
  accuracy)
    # the full sweep alone (~430 s on an H200 with a cold kernel cache); RESUME=1 continues a cut run in the same OUTDIR
    T=${T_ACC:-560} run python -m pipelines.cli report accuracy --sweep full --reference-max-frames ${REF_FRAMES:-150} \
      --device cuda:0 --out "$out/accuracy" --no-progress ${RESUME:+--resume} ;;
  reports)
    # full matrix: 12 s on an H200; full sweep: reference ~0.65 s/frame (40x100 iterations), mass-spring
    # ~87 s per tolerance, the rest ~70 s; rows land in accuracy_rows.jsonl as they finish
    T=120 run python -m pipelines.cli report stability --size full --device cuda:0 --out "$out/stability" --no-progress
    T=${T_ACC:-450} run python -m pipelines.cli report accuracy --sweep ${SWEEP:-full} --reference-max-frames ${REF_FRAMES:-150} \
      --device cuda:0 --out "$out/accuracy" --no-progress ;;
  dataset-scale)
    # the shipped spec at full width: 240 tasks of <= 30 poses as parallel worlds (heartbeat every 20 s);
    # EXTRA passes more bench flags, e.g. EXTRA="--sim contact.self_contact=true"
    T=${T:-560} run python bench/bench_dataset.py --spec tailornet-tshirt --poses ${POSES:-240} --test-poses 30 \
      --sim poses_per_task=${PER_TASK:-30} --device cuda:0 --out /tmp/tn-scale ${KEEP:+--keep} ${EXTRA:-} ;;
  dataset-full)
    # the whole shipped spec (58,900 target poses) in 30-pose tasks that refill 256 worlds, cut by T seconds
    # (T=585 lets it finish on a warm H200: 513 s of wall time with the 15 x 5 spec):
    # the steady-state rate of the full job (the bench prints a partial JSON line when timeout stops it)
    # (where the device's time goes: EXTRA="--device-profile $OUT/device_profile.json --device-profile-window 100:20")
    T=${T:-560} run python bench/bench_dataset.py --spec tailornet-tshirt --poses 2600 --test-poses 179 \
      --sim poses_per_task=${PER_TASK:-30} --device cuda:0 --out /tmp/tn-full ${KEEP:+--keep} ${EXTRA:-} ;;
  self-contact)
    # the same slice (20+20 pairs, POSES train poses per pair, 30-pose tasks) without and with self-contact:
    # what it does to the self-intersection drops, explosions and time; EXTRA passes more bench flags to both,
    # e.g. EXTRA="--sim solver=vbd"
    for sc in ${SC:-false true}; do
      T=${T:-270} run python bench/bench_dataset.py --spec tailornet-tshirt --poses ${POSES:-40} --test-poses ${TEST_POSES:-10} \
        --sim poses_per_task=30 --sim contact.self_contact=$sc --device cuda:0 --out /tmp/tn-sc-$sc ${EXTRA:-}
    done ;;
  profile-self-contact)
    # a frame's GPU time by kernel, 240 t-shirts (7.7k), without and with self-contact
    for sc in "" --self-contact; do
      T=150 run python bench/bench_sim_throughput.py --device cuda:0 --scene tshirt --resolution 7700 --worlds 240 \
        --frames 10 --profile $sc --out "$jl"
    done ;;
  *) echo "unknown stage $stage"; exit 2 ;;
esac
# JSON lines the benches printed but did not write with --out themselves (no duplicates)
touch "$jl"; grep -h '^{' "$log" 2>/dev/null | awk 'FILENAME != "-" { seen[$0]; next } !($0 in seen)' "$jl" - >>"$jl" || true
tail -c 6000 "$log"
