#!/usr/bin/env bash
# Jobs longer than one device call (10 minutes): start one in the background, then wait for it in
# calls made back to back (the machine is given back after 30 s idle), each returning where it is.
#
#   bash bench/device_job.sh start NAME COMMAND...   # COMMAND runs from a snapshot of the checkout
#   bash bench/device_job.sh wait NAME [SECONDS]     # up to SECONDS (default 540), then the log's tail
#   bash bench/device_job.sh collect NAME            # the job's directory as $OUT/NAME.tgz (one file:
#                                                    # a call brings back only a few files)
#
# The job runs in /root/jobs/NAME/snap (a copy of the working tree, so later calls may change it)
# with PYTHONPATH=/tmp/site:SNAP (pack.sh's packages); COMMAND's own files go under $JOB
# (/root/jobs/NAME/out), its output to /root/jobs/NAME/log, its exit status to /root/jobs/NAME/rc.
#
# The learners at full scale on 4 GPUs (the t-shirt spec, then TailorNet, uvimage, the data floor and
# collision_aware, or with TN2_CONFIG a second TailorNet, on one GPU each, evaluated side by side):
#   bash bench/device_job.sh start learn bash bench/device_job.sh learners-full 4
# The 1-vs-4 GPU generation ratio, then the learners on the 4-GPU dataset, in one job:
#   bash bench/device_job.sh start learn bash -c "python bench/bench_scale_out.py --gpus 4 --local-batches 1 \
#     --skip-train --out /root/jobs/scale > \$JOB/scale.json; LEARN_DATA=/root/jobs/scale/ray4 \
#     bash bench/device_job.sh learners-full 4"
# TailorNet on GPU 0 beside collision_aware over GPUs 1-3 (torchrun), on the t-shirt spec made on 4 GPUs:
#   CA_SECONDS=660 bash bench/device_job.sh start learn bash bench/device_job.sh learners-ca 4
# (CA_VARIANTS="vae: {kl: 1.0e-4}; regressor: {target: canonical}": then VAE and regressor variants on its projections)
# (SPEC_POSES=800: 800 train poses per pair, a third of the targets)
# (PROJECTION_BENCH=0: the generation alone on the 4 GPUs) and beside it, once training starts, the
# one-GPU run of that plan's first batch on GPU 3 for the 1-vs-4 generation ratio:
#   AFTER=/root/jobs/learn/out/training.started bash bench/device_job.sh start ratio bash bench/device_job.sh ratio
# Training's 1-vs-2-vs-4 GPU epoch rate (TailorNet) on the whole t-shirt spec made on 4 GPUs:
#   GPU_TESTS="tests/test_collision_aware.py" bash bench/device_job.sh start scale bash bench/device_job.sh scale-train 4
# Generation of one cloth3d garment type (C3_TYPE, default top) on 1, 2 and 4 GPUs:
#   bash bench/device_job.sh start c3 bash bench/device_job.sh type-scale 4
# collision_aware alone on a reduced t-shirt spec (one GPU):
#   bash bench/device_job.sh start ca bash bench/device_job.sh ca-small
# Solver settings side by side on the 7.7k t-shirt slice (240 targets), one after another on one GPU:
#   SLICES="; --sim solver=vbd --sim substeps=20 --sim iterations=3" bash bench/device_job.sh start sl bash bench/device_job.sh slices
set -uo pipefail
cmd=${1:?start|wait|collect|learners-full|learners-ca|scale-train|type-scale|ca-variants|ca-small|ratio|slices}; name=${2:-}
stamp() { while IFS= read -r line; do printf '%s %s\n' "$(date +%T)" "$line"; done; }  # lines with the clock time
train_ca() {  # DATA DEVICE [TIMEOUT]: collision_aware into $JOB/ca, CA_EPOCHS for every stage (default:
  # each stage's own, or CA_CONFIG's), CA_CONFIG as YAML overrides, stopped after TIMEOUT seconds (no model then), its lines stamped;
  # with several GPUs in CUDA_VISIBLE_DEVICES, one torchrun process on each
  echo "${CA_CONFIG:-"{}"}" > "$JOB/ca.yaml"
  local visible=${CUDA_VISIBLE_DEVICES:-0} launch=(python)
  local n=$(( $(printf %s "$visible" | tr -cd , | wc -c) + 1 ))
  [ "$2" != cuda ] || [ "$n" = 1 ] || launch=(python -m torch.distributed.run --standalone --nproc-per-node "$n")
  timeout "${3:-0}" "${launch[@]}" -m pipelines.cli train collision_aware --data "$1" --out "$JOB/ca" --device "$2" \
    ${CA_EPOCHS:+--epochs "$CA_EPOCHS"} --config "$JOB/ca.yaml" 2>&1 | stamp > "$JOB/train_collision_aware.log"
}
ca_variant() {  # DIR GPU VARIANT DATA [COPY]: collision_aware with VARIANT (YAML overrides of CA_CONFIG)
  # into DIR on GPU, then evaluated; COPY=1: on $JOB/ca's SDF and, unless VARIANT sets fields, its
  # fields (and so its cached projections), and unless it sets fields or vae, its VAE (a variant of
  # the regressor alone trains only the regressor); train_variants.log gets a summary line
  local dir=$1 variant=$3
  mkdir -p "$dir"
  if [ "${5:-0}" = 1 ]; then
    cp "$JOB"/ca/sdf.* "$dir/"
    printf %s "$variant" | grep -q 'fields:' || cp "$JOB"/ca/fields.* "$dir/"
    printf %s "$variant" | grep -q -E 'fields:|vae:' || cp "$JOB"/ca/vae.* "$JOB"/ca/vae_* "$dir/" 2>/dev/null
  fi
  python -c "import sys, yaml; base = yaml.safe_load(sys.argv[1]) or {}; over = yaml.safe_load(sys.argv[2]) or {}
for stage, values in over.items(): base.setdefault(stage, {}).update(values)
yaml.safe_dump(base, open(sys.argv[3], 'w'))" "${CA_CONFIG:-"{}"}" "$variant" "$dir/config.yaml"
  export CUDA_VISIBLE_DEVICES=$2
  python -m pipelines.cli train collision_aware --data "$4" --out "$dir" --device cuda ${CA_EPOCHS:+--epochs "$CA_EPOCHS"} \
    --config "$dir/config.yaml" --no-progress > "$dir/train.log" 2>&1
  python -m pipelines.cli evaluate "$dir" --data "$4" --device cuda --renders 0 > "$dir/evaluate.log" 2>&1
  echo "$(basename "$dir") ($variant): $(grep -E '^(train_test|test_train|test_test) ' \
    "$dir/evaluate.log" | awk '{printf "%s %s mm %s %%; ", $1, $3, $6}')" >> "$JOB/train_variants.log"
}
ca_variants() {  # GPUS DATA: each of CA_VARIANTS (';'-separated YAML overrides of CA_CONFIG, e.g.
  # "vae: {hidden_size: 1024}; regressor: {target: canonical}") by ca_variant into $JOB/variantK on
  # $JOB/ca's SDF and fields (a variant that sets fields trains its own), one per GPU at a time
  local k=0 pids=() variant
  IFS=';' read -ra variants <<< "$CA_VARIANTS"
  for variant in "${variants[@]}"; do
    (ca_variant "$JOB/variant$k" $((k % $1)) "$variant" "$2" "$([ -f "$JOB/ca/sdf.pt" ] && echo 1 || echo 0)") &
    pids+=($!)
    k=$((k + 1))
    if [ $((k % $1)) = 0 ]; then wait "${pids[@]}"; pids=(); fi
  done
  wait "${pids[@]}"
}
generate_full() {  # GPUS DATA: the shipped t-shirt spec (audit off) on GPUS GPUs with Ray into DATA; with
  # SPEC_POSES=P, P train poses per pair and 60 test poses (20 of them on the test pairs' test_train)
  python - "$JOB/spec.yaml" "$1" "${SPEC_POSES:-0}" <<'PY'
import sys, yaml
from pipelines.spec import load_spec
spec = load_spec("tailornet-tshirt")
spec["audit"]["samples"] = 0
spec["simulation"]["batches"] = int(sys.argv[2])
if int(sys.argv[3]):
    spec["poses"].update(train_count=int(sys.argv[3]), test_count=60)
    spec["splits"].update(test_train=20, test_test=60)
yaml.safe_dump(spec, open(sys.argv[1], "w"))
PY
  python -m pipelines.cli generate-dataset "$JOB/spec.yaml" --out "$2" --executor ray --no-progress > "$JOB/generate.log" 2>&1
}
type_spec() {  # FILE TYPE BATCHES: one garment type of the shipped cloth3d spec (500 motion sequences of
  # 60 frames, 2,000 vertices), its plan in BATCHES batches, audit off
  python - "$1" "$2" "$3" <<'PY'
import sys, yaml
from pipelines.spec import load_spec
from simulate.garment.cloth3d import allowed_fabrics
spec = load_spec("cloth3d")
kind = sys.argv[2]
spec["name"] = f"cloth3d-{kind}"
spec["garment"]["type"] = kind
spec["garment"]["fabric"] = list(allowed_fabrics(kind, spec["garment"]["fabric"]))  # tops: cotton or silk
spec["audit"]["samples"] = 0
spec["simulation"]["batches"] = int(sys.argv[3])
yaml.safe_dump(spec, open(sys.argv[1], "w"))
PY
}
root=/root/jobs/$name
case $cmd in
  start)
    shift 2
    rm -rf "$root" && mkdir -p "$root/snap" "$root/out"
    tar --exclude=./.device --exclude=./.venv -cf - . | tar -xf - -C "$root/snap"
    (cd "$root/snap" && JOB="$root/out" PYTHONPATH="/tmp/site:$root/snap" PYTHONUNBUFFERED=1 TQDM_DISABLE=1 \
      NCCL_NVLS_ENABLE=0 TORCH_SYMM_MEM_DISABLE_MULTICAST=1 NVSHMEM_DISABLE_NVLS=1 \
      setsid nohup bash -c '"$@"; echo $? > '"$root/rc" _ "$@" > "$root/log" 2>&1 < /dev/null &)
    echo "started $name: $*" ;;
  wait)
    end=$(( $(date +%s) + ${3:-540} ))
    while [ ! -f "$root/rc" ] && [ "$(date +%s)" -lt "$end" ]; do sleep 5; done
    [ -f "$root/rc" ] && echo "$name finished: rc=$(cat "$root/rc")" || echo "$name still running"
    tail -n 15 "$root/log"
    nvidia-smi --query-gpu=index,utilization.gpu,memory.used --format=csv,noheader 2>/dev/null || true ;;
  collect)
    # checkpoints stay behind (GBs at full scale: over what a call brings back), so a collect made
    # while a job still trains returns its logs
    tar -czf "${OUT:?}/$name.tgz" --exclude='*.pt' -C /root/jobs "$name/log" "$name/out" 2>/dev/null
    ls -la "$OUT/$name.tgz" ;;
  learners-full)
    # (inside a job) generate the shipped t-shirt spec on N GPUs with Ray (audit off), then side by
    # side: TailorNet at the paper's epochs on GPU 0, uvimage on GPU 1 (as many epochs as fit
    # UV_SECONDS, default 400, after a one-epoch probe), the data floor on GPU 2, collision_aware (or
    # with TN2_CONFIG a second TailorNet) on GPU 3; UV_SECONDS=0 skips uvimage, and with TN2_CONFIG
    # puts collision_aware on GPU 1. Then one evaluation of the models with --analysis and --floor
    # (and one of the second TailorNet). Logs, loss curves, floor.json and evaluation.json under $JOB.
    # LEARN_DATA=DIR trains on an existing dataset instead (e.g. bench_scale_out.py's OUT/ray4).
    gpus=${2:-4}
    ds=${LEARN_DATA:-/root/jobs/data-tshirt}
    [ -n "${LEARN_DATA:-}" ] || generate_full "$gpus" $ds
    (CUDA_VISIBLE_DEVICES=2 python -m pipelines.cli report floor --data $ds --out "$JOB/floor" --device cuda:0 \
      --train-device cuda --pairs 8 --targets 8 --no-progress > "$JOB/floor.log" 2>&1) &
    floor=$!
    if [ -n "${TN2_CONFIG:-}" ]; then
      # GPU 3: a second TailorNet with the --config settings TN2_CONFIG gives as YAML (e.g.
      # "model: {canonical_repeat: 0}", the paper's protocol), evaluated on its own at the end
      echo "$TN2_CONFIG" > "$JOB/tn2.yaml"
      (CUDA_VISIBLE_DEVICES=3 python -m pipelines.cli train tailornet --data $ds --out "$JOB/tn2" --device cuda \
        --config "$JOB/tn2.yaml" --no-progress > "$JOB/train_tailornet2.log" 2>&1) &
    fi
    uv_seconds=${UV_SECONDS:-400}
    # collision_aware (seed 002) on GPU 3, or beside a second TailorNet on GPU 1 when uvimage leaves it free
    ca_gpu=3
    [ -n "${TN2_CONFIG:-}" ] && { ca_gpu=; [ "$uv_seconds" = 0 ] && ca_gpu=1; }
    ca=
    if [ -n "$ca_gpu" ]; then
      (CUDA_VISIBLE_DEVICES=$ca_gpu train_ca $ds cuda "${CA_SECONDS:-900}") &
      ca=$!
    fi
    uv=
    [ "$uv_seconds" = 0 ] || (export CUDA_VISIBLE_DEVICES=1
     python -m pipelines.cli train uvimage --data $ds --out "$JOB/uv_probe" --device cuda --epochs 1 --no-progress \
       > "$JOB/train_uvimage_probe.log" 2>&1
     epochs=$(python -c "import csv, sys; s = float(list(csv.reader(open(sys.argv[1])))[-1][2]); \
print(max(1, min(100, int(float(sys.argv[2]) / s))))" "$JOB/uv_probe/uvimage_loss.csv" "$uv_seconds")
     python -m pipelines.cli train uvimage --data $ds --out "$JOB/uv" --device cuda --epochs "$epochs" \
       --no-progress > "$JOB/train_uvimage.log" 2>&1) &
    [ "$uv_seconds" = 0 ] || uv=$!
    CUDA_VISIBLE_DEVICES=0 python -m pipelines.cli train tailornet --data $ds --out "$JOB/tn" --device cuda \
      --no-progress > "$JOB/train_tailornet.log" 2>&1
    wait $uv $floor $ca
    # one run directory: the evaluation puts them side by side
    cp "$JOB/uv/uvimage_model.pt" "$JOB/tn/" 2>/dev/null || echo "uvimage: not trained (UV_SECONDS=0)"
    # the SDF too: drape evaluate reports collision_aware's canonical collision rate with it
    cp "$JOB/ca/collision_aware_model.pt" "$JOB/ca/sdf.pt" "$JOB/ca/sdf.done" "$JOB/tn/" 2>/dev/null \
      || echo "collision_aware: no model (see its log)"
    CUDA_VISIBLE_DEVICES=0 python -m pipelines.cli evaluate "$JOB/tn" --data $ds --device cuda --analysis \
      --floor "$JOB/floor/floor.json" > "$JOB/evaluate.log" 2>&1
    if [ -n "${TN2_CONFIG:-}" ]; then
      CUDA_VISIBLE_DEVICES=0 python -m pipelines.cli evaluate "$JOB/tn2" --data $ds --device cuda --analysis \
        > "$JOB/evaluate_tn2.log" 2>&1
    fi
    find "$JOB" -name "*.pt" -delete  # checkpoints stay off the way back (GBs at full scale)
    ;;
  learners-ca)
    # (inside a job) the shipped t-shirt spec on N GPUs with Ray (audit off; SPEC_POSES as in
    # generate_full; LEARN_DATA=DIR: an existing dataset instead), while bench/bench_projection.py times the projection step on GPU 0;
    # then TailorNet at the paper's epochs on GPU 0 beside collision_aware over GPUs 1..N-1 with
    # torchrun (stopped after CA_SECONDS, default 900; CA_EPOCHS, CA_CONFIG as in train_ca); then one
    # evaluation of both with --analysis; then, with CA_VARIANTS, ca_variants on the same projections
    # (CA_BESIDE: a whole second collision_aware on GPU 0 after TailorNet, see below).
    gpus=${2:-4}
    ds=${LEARN_DATA:-/root/jobs/data-tshirt}
    if [ -z "${LEARN_DATA:-}" ]; then
      generate_full "$gpus" $ds &
      gen=$!
      # PROJECTION_BENCH=0: no projection timing beside the generation (its GPU 0 then simulates
      # alone, so the generation's rate is that of N GPUs, e.g. for the ratio job below)
      if [ "${PROJECTION_BENCH:-1}" = 1 ]; then
        CUDA_VISIBLE_DEVICES=0 python bench/bench_projection.py --gpus $((gpus - 1)) > "$JOB/projection_bench.json" \
          2> "$JOB/projection_bench.err"
        cat "$JOB/projection_bench.json"
      fi
      wait $gen
    fi
    # a call made while the data generates may still change CA_CONFIG, CA_SECONDS, CA_GPUS (e.g.
    # 0,1,2,3) or TN=0 (no TailorNet) by writing them to $JOB/plan.sh, once the step's time is known
    CA_GPUS=${CA_GPUS:-$(seq -s, 1 $((gpus - 1)))}
    TN=1
    [ -f "$JOB/plan.sh" ] && { . "$JOB/plan.sh"; cat "$JOB/plan.sh"; }
    echo "$(date +%T) training"
    touch "$JOB/training.started"  # what a job started with AFTER=.../training.started waits for
    (CUDA_VISIBLE_DEVICES=$CA_GPUS train_ca $ds cuda "${CA_SECONDS:-900}") &
    ca=$!
    if [ "$TN" = 1 ]; then
      CUDA_VISIBLE_DEVICES=0 python -m pipelines.cli train tailornet --data $ds --out "$JOB/tn" --device cuda \
        --no-progress > "$JOB/train_tailornet.log" 2>&1
    fi
    # CA_BESIDE (YAML overrides of CA_CONFIG): after TailorNet, a whole second collision_aware (its
    # own fields and SDF) on GPU 0 into $JOB/beside while the first still trains, then evaluated
    [ -z "${CA_BESIDE:-}" ] || (ca_variant "$JOB/beside" 0 "$CA_BESIDE" $ds)
    wait $ca
    echo "$(date +%T) evaluating"
    mkdir -p "$JOB/tn"
    cp "$JOB/ca/collision_aware_model.pt" "$JOB/ca/template.npz" "$JOB/ca/sdf.pt" "$JOB/ca/sdf.done" "$JOB/tn/" 2>/dev/null \
      || echo "collision_aware: no model (see its log)"
    CUDA_VISIBLE_DEVICES=0 python -m pipelines.cli evaluate "$JOB/tn" --data $ds --device cuda --analysis \
      > "$JOB/evaluate.log" 2>&1
    [ -z "${CA_VARIANTS:-}" ] || ca_variants "$gpus" $ds
    find "$JOB" -name "*.pt" -delete
    ;;
  scale-train)
    # (inside a job) the training's epoch rate at 1, 2 and N GPUs on the whole t-shirt spec: the spec
    # generated on N GPUs with Ray (generate_full; LEARN_DATA=DIR: an existing dataset), with GPU_TESTS
    # (pytest paths, e.g. the CUDA cases of tests/test_collision_aware.py) on GPU 0 beside it; then
    # bench_scale_out.py --pack over TRAIN_GPUS (default 2,N) and TRAIN_PROCESSES (tailornet: process
    # counts above N, sharing the GPUs) with LEARNER (default tailornet): 1 and 2 processes side by
    # side on GPUs 0 and 1-2, then N; then each run evaluated, the runs side by side on their own
    # GPUs (the N-GPU model should match the 1-GPU one). JSON in $JOB/scale_train.json. TRAIN_BESIDE:
    # a command on GPU N-1 while 1 and 2 processes train (e.g. python bench/bench_hf_epoch.py --device cuda).
    # C3_TYPE=top: also the cloth3d type's generation on N GPUs, and its first batch on one GPU beside
    # the pack ($JOB/c3_ratio.json).
    gpus=${2:-4}
    ds=${LEARN_DATA:-/root/jobs/data-tshirt}
    if [ -z "${LEARN_DATA:-}" ]; then
      generate_full "$gpus" $ds &
      gen=$!
      # shellcheck disable=SC2086  # GPU_TESTS: several paths or node ids
      [ -z "${GPU_TESTS:-}" ] || (CUDA_VISIBLE_DEVICES=0 python -m pytest -q -p no:cacheprovider $GPU_TESTS \
        > "$JOB/gpu_tests.log" 2>&1; tail -n 3 "$JOB/gpu_tests.log")
      wait $gen
      grep -E "kept|wall" "$JOB/generate.log" | tail -n 4
    fi
    beside=${TRAIN_BESIDE:-}
    if [ -n "${C3_TYPE:-}" ]; then
      # the cloth3d type on N GPUs with Ray now, and beside the 1+2 pack its plan's first batch on
      # the last GPU alone (bench_scale_out --ray-data: the 1-vs-N ratio of the type-scale mode)
      echo "$(date +%T) cloth3d $C3_TYPE on $gpus GPUs"
      type_spec "$JOB/type_spec.yaml" "$C3_TYPE" "$gpus"
      python -m pipelines.cli generate-dataset "$JOB/type_spec.yaml" --out "/root/jobs/c3-ray$gpus" --executor ray \
        --no-progress > "$JOB/c3_generate.log" 2>&1
      grep -E "kept|wall" "$JOB/c3_generate.log" | tail -n 2
      beside=${beside:-"python bench/bench_scale_out.py --spec $JOB/type_spec.yaml --gpus $gpus --local-batches 1 \
        --ray-data /root/jobs/c3-ray$gpus --skip-train --out /root/jobs/c3-ratio > $JOB/c3_ratio.json"}
    fi
    echo "$(date +%T) training"
    scale=/root/jobs/scale-train
    # TRAIN_BESIDE: a command on the last GPU, which the pack leaves free while 1 and 2 processes
    # train, cut at BESIDE_TIMEOUT s (default 300; 450 with C3_TYPE: one process trains ~470 s) so
    # that it never overlaps the N-GPU run; output in $JOB/beside.log
    [ -z "$beside" ] || (CUDA_VISIBLE_DEVICES=$((gpus - 1)) timeout "${BESIDE_TIMEOUT:-$([ -n "${C3_TYPE:-}" ] \
      && echo 450 || echo 300)}" bash -c "$beside" > "$JOB/beside.log" 2>&1) &
    python bench/bench_scale_out.py --skip-generate --data $ds --gpus "${TRAIN_GPUS:-2,$gpus}" --pack \
      ${TRAIN_PROCESSES:+--processes "$TRAIN_PROCESSES"} --learner "${LEARNER:-tailornet}" --out $scale \
      > "$JOB/scale_train.json" 2> "$JOB/scale_train.err"
    tail -n 4 "$JOB/scale_train.err"
    echo "$(date +%T) evaluating"
    k=0
    for run in $scale/train-w*/; do
      w=$(basename "$run"); mkdir -p "$JOB/$w"
      cp "$run"/*.csv "$run"/run.json "$JOB/$w/" 2>/dev/null; cp $scale/"$w".log "$JOB/$w/train.log" 2>/dev/null
      (CUDA_VISIBLE_DEVICES=$((k % gpus)) python -m pipelines.cli evaluate "$run" --data $ds --device cuda --renders 0 \
        > "$JOB/$w/evaluate.log" 2>&1) &
      k=$((k + 1))
    done
    wait
    for w in "$JOB"/train-w*/; do echo "$(basename "$w"): $(grep -E '^(train_test|test_train|test_test) ' "$w/evaluate.log" | tr -s ' ' | tr '\n' ';')"; done
    ;;
  ca-variants)
    # (inside a job) CA_VARIANTS alone on the dataset LEARN_DATA over N GPUs (ca_variants; each
    # variant trains its own fields and SDF, there being no $JOB/ca)
    ca_variants "${2:-1}" "${LEARN_DATA:?LEARN_DATA: the dataset}" ;;
  ca-small)
    # (inside a job) collision_aware alone on a reduced t-shirt spec: CA_POSES train poses per train
    # pair (default 150), 40 test poses (fewer with fewer train poses), the garment at CA_RESOLUTION
    # vertices (default the spec's), on CA_DEVICE (default cuda), generated into
    # /root/jobs/data-ca-small (CA_DATA=DIR: an existing dataset instead); CA_EPOCHS and CA_CONFIG as
    # in train_ca; then `drape evaluate`. The stage times are the clock stamps of
    # train_collision_aware.log; the log gets the summary lines.
    dev=${CA_DEVICE:-cuda}
    python - "$JOB/spec.yaml" "${CA_POSES:-150}" "${CA_RESOLUTION:-0}" "$dev" <<'PY'
import sys, yaml
from pipelines.spec import load_spec
spec = load_spec("tailornet-tshirt")
spec["audit"]["samples"] = 0
poses = int(sys.argv[2])
spec["poses"].update(train_count=poses, test_count=min(40, 2 * poses))
spec["splits"].update(test_train=min(20, poses), test_test=min(40, 2 * poses))
if int(sys.argv[3]):
    spec["garment"]["resolution"] = int(sys.argv[3])
spec["simulation"]["device"] = sys.argv[4]
yaml.safe_dump(spec, open(sys.argv[1], "w"))
PY
    ds=${CA_DATA:-/root/jobs/data-ca-small}
    if [ -z "${CA_DATA:-}" ]; then
      echo "$(date +%T) generating"
      python -m pipelines.cli generate-dataset "$JOB/spec.yaml" --out "$ds" --no-progress > "$JOB/generate.log" 2>&1
      grep -E "frames kept|this run|total wall" "$JOB/generate.log"
    fi
    echo "$(date +%T) training collision_aware"
    train_ca "$ds" "$dev"
    grep -vi "warn\|sparse_coo" "$JOB/train_collision_aware.log" | tail -n 4
    echo "$(date +%T) evaluating"
    python -m pipelines.cli evaluate "$JOB/ca" --data "$ds" --device "$dev" --renders 0 > "$JOB/evaluate.log" 2>&1
    grep -E "collision_aware|evaluation:" "$JOB/evaluate.log"
    ;;
  type-scale)
    # (inside a job) generation on 1, 2 and N GPUs (default 4) of one garment type of the shipped
    # `cloth3d` spec (C3_TYPE, default top: 500 motion sequences of 60 frames, 2,000 vertices), its
    # plan in N batches, audit off: bench_scale_out.py --gpus 2,N --skip-train, JSON in $JOB/type_scale.json
    gpus=${2:-4}
    type_spec "$JOB/type_spec.yaml" "${C3_TYPE:-top}" "$gpus"
    python bench/bench_scale_out.py --spec "$JOB/type_spec.yaml" --gpus "2,$gpus" --skip-train --out /root/jobs/type-scale \
      > "$JOB/type_scale.json" 2> "$JOB/type_scale.err"
    tail -n 3 "$JOB/type_scale.err"; grep -o -E '"(kept_frames_per_s|speedup|simulation_s)": [0-9.]+' "$JOB/type_scale.json"
    ;;
  ratio)
    # (inside a job) the 1-vs-N GPU generation ratio on a GPU other work leaves free: once AFTER exists
    # (e.g. /root/jobs/learn/out/training.started), bench_scale_out.py's local run of the plan's first
    # batch on GPU RATIO_GPU (default 3), compared with the Ray dataset RAY_DATA (default
    # /root/jobs/data-tshirt) of the spec RATIO_SPEC (default /root/jobs/learn/out/spec.yaml); JSON in $JOB/scale.json
    [ -z "${AFTER:-}" ] || { while [ ! -e "$AFTER" ]; do sleep 5; done; }
    echo "$(date +%T) local run of batch 0"
    CUDA_VISIBLE_DEVICES=${RATIO_GPU:-3} python bench/bench_scale_out.py --spec "${RATIO_SPEC:-/root/jobs/learn/out/spec.yaml}" \
      --gpus 4 --local-batches 1 --ray-data "${RAY_DATA:-/root/jobs/data-tshirt}" --skip-train --out /root/jobs/ratio \
      > "$JOB/scale.json" 2> "$JOB/scale.err"
    tail -n 3 "$JOB/scale.err"; grep -E '"(kept_frames_per_s|speedup|simulation_s)"' "$JOB/scale.json"
    ;;
  slices)
    # (inside a job) bench/bench_dataset.py on the t-shirt spec's slice of 4 train and 2 test poses per
    # pair (240 targets, 256 worlds, audit off), once per entry of SLICES (';'-separated bench_dataset
    # options; an empty entry is the spec as shipped), one after another on GPU SLICE_GPU (default 0),
    # once the file AFTER exists where given (e.g. another job's training.started, so the slices
    # take a GPU that job leaves free). One JSON line per entry in $JOB/slices.jsonl, with its options.
    python - "$JOB/slice_spec.yaml" <<'PY'
import sys, yaml
from pipelines.spec import load_spec
spec = load_spec("tailornet-tshirt")
spec["audit"]["samples"] = 0
yaml.safe_dump(spec, open(sys.argv[1], "w"))
PY
    [ -z "${AFTER:-}" ] || { while [ ! -e "$AFTER" ]; do sleep 5; done; }
    IFS=';' read -ra slices <<< "${SLICES:?SLICES: ';'-separated bench_dataset.py options}"
    for options in "${slices[@]}"; do
      echo "$(date +%T) slice: ${options:-the spec as shipped}"
      # shellcheck disable=SC2086  # the entry's options split into words
      result=$(CUDA_VISIBLE_DEVICES=${SLICE_GPU:-0} python bench/bench_dataset.py --spec "$JOB/slice_spec.yaml" \
        --poses 4 --test-poses 2 --device cuda:0 --out /root/jobs/slice_out $options 2>> "$JOB/slices.err")
      python -c "import json, sys; r = json.loads(sys.argv[1] or '{}'); r['options'] = sys.argv[2]; print(json.dumps(r))" \
        "$(printf %s "$result" | tail -n 1)" "$options" >> "$JOB/slices.jsonl"
      tail -n 1 "$JOB/slices.jsonl" | cut -c 1-400
    done
    ;;
  *) echo "unknown command $cmd (start, wait, collect, learners-full, learners-ca, scale-train, ca-variants, ca-small, ratio, slices)" >&2; exit 2 ;;
esac
