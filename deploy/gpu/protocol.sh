#!/usr/bin/env bash
# The paper's protocol on one NVIDIA GPU, in one go (docs/gpu.md):
#
#   1. gsplat's CUDA extension built (once per machine, in the background);
#   2. the Triton kernels (the Fisher's, the anchor's proxy ψ's) tested against the torch
#      reference on the GPU;
#   3. bench latency at the first size (every method's selection time, its ratios to the
#      full-pool EIG and FisherRF, and the slow @paper variants) while gsplat builds;
#   4. bench run --profile paper, shortened (SHORT below), on an object and a capture, every
#      method and the @paper variants, one seed, one process per run, then the tables;
#   5. alone on the GPU: bench latency at the other sizes (and the largest at LATENCY_WIDE's
#      1024x768), the other CUDA tests (TESTS), and
#      bench render at 100k and 1M Gaussians, 512x512 and 1024x768 (this project's rasterizer
#      and Fisher, the Fisher's torch reference, gsplat, a mapper training step against
#      gsplat's own step, the anchor's proxy ψ over the pool and its gradient against their
#      torch reference).
#
# Needs python3 with a CUDA torch and this package (pip install -e '.[service,lab,cuda]') and a CUDA
# toolkit for gsplat's build. Everything lands in $OUT (default gpu-out); each step has a time
# limit so that one slow step cannot starve the rest (DEADLINE: seconds for the whole script).
# GSPLAT_SITE (optional): a folder holding gsplat, put on PYTHONPATH only once its extension has
# built, so that a failed build is not retried by every step (they train with the builtin
# rasterizer instead). The sizes are variables: DEVICE=cpu with small ones is the smoke test
# that tests/e2e/test_gpu_protocol.py runs.
set -u
OUT=${OUT:-gpu-out}
PY=${PYTHON:-python3}
DEADLINE=${DEADLINE:-560}
DEVICE=${DEVICE:-cuda}
S=lab/scenes
SCENE_OBJECT=${SCENE_OBJECT:-$S/spot}
OBJECT_SPLAT=${OBJECT_SPLAT:-$SCENE_OBJECT/spot_10k.splat}
SCENE_CAPTURE=${SCENE_CAPTURE:-$S/skull_photos}
LATENCY_SIZES=${LATENCY_SIZES:-100000 1000000}
LATENCY=${LATENCY:---width 512 --height 512 --pool 100 --events 2}
LATENCY_METHODS=${LATENCY_METHODS:-random,fisherrf,cover,full_eig,agile,agile_plus,agile@eig,agile_plus@eig}
LATENCY_SLOW=${LATENCY_SLOW-agile@paper,agile_plus@paper}
LATENCY_WIDE=${LATENCY_WIDE---width 1024 --height 768 --pool 100 --events 2}
RENDER=${RENDER:---gaussians 100000,1000000 --sizes 512,1024x768 --repeats 10}
PROFILE=${PROFILE:-paper}
SHORT=${SHORT---pool-size 64 --view-budget 20 --interval 200 --steps 2200}
OBJECT_RES=${OBJECT_RES:-512}
CAPTURE_RES=${CAPTURE_RES:-240}
METHODS=${METHODS:-random fisherrf cover full_eig agile agile_plus agile@paper agile_plus@paper}
SEEDS=${SEEDS:-0}
TESTS=${TESTS-tests/nbv/test_cuda.py tests/nbv/test_se3.py tests/mapper/test_gsplat_render.py tests/sessions/test_device.py}
TESTS_S=${TESTS_S:-150}
mkdir -p "$OUT/logs"
export PYTHONUNBUFFERED=1
T0=$(date +%s)
elapsed() { echo $(($(date +%s) - T0)); }
left() { echo $((DEADLINE - $(elapsed))); }
say() { echo "[$(elapsed) s] $*" | tee -a "$OUT/steps.txt"; }
AG="$PY -m agilegs.service.cli"  # a command, not a shell function: timeout runs it

say "device: $(nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv,noheader 2>&1 | head -1)"
say "torch $("$PY" -c 'import torch; print(torch.__version__, torch.version.cuda)'), nvcc: $(nvcc --version 2>&1 | tail -1)"
say "commit ${COMMIT:-$(git rev-parse --short HEAD 2>/dev/null || echo unknown)}"

# 1. gsplat's extension, in the background while the selections are timed
export MAX_JOBS=${MAX_JOBS:-12}
if [ "$DEVICE" != cpu ]; then
  export TORCH_CUDA_ARCH_LIST=${TORCH_CUDA_ARCH_LIST:-$("$PY" -c 'import torch; print("%d.%d" % torch.cuda.get_device_capability())')}
fi
(
  t=$(date +%s)
  [ -n "${GSPLAT_SITE:-}" ] && export PYTHONPATH="$GSPLAT_SITE${PYTHONPATH:+:$PYTHONPATH}"
  "$PY" -c 'from gsplat.cuda._backend import _C; assert _C is not None' >"$OUT/logs/gsplat-build.txt" 2>&1
  echo "gsplat build: exit $? in $(($(date +%s) - t)) s" >>"$OUT/logs/gsplat-build.txt"
) &
BUILD=$!

# 2. the Triton kernels against the torch reference on this GPU, first: where the Fisher's
#    fail, everything after runs on the pure-torch Fisher (AGILEGS_KERNELS=torch); where the
#    anchor's proxy ψ's fail, the anchor's ψ runs in torch (AGILEGS_GPU_ANCHOR=0); each says
#    so. A test run that fails (exit 1) or times out turns its kernels off; one that cannot
#    collect its tests (tests/conftest.py imports the whole service: a missing wheel) keeps
#    them and says they are untested (bench render's agree columns still compare them)
triton_tests() {  # name log file off-variable off-value
  timeout 150 "$PY" -m pytest -q -p no:cacheprovider -m cuda -rA "$3" >"$OUT/logs/$2" 2>&1
  local rc=$?
  say "Triton $1 tests: exit $rc ($(tail -1 "$OUT/logs/$2"))"
  if [ $rc = 1 ] || [ $rc = 124 ]; then
    export "$4=$5"; say "the $1 runs in pure torch ($4=$5)"
  elif [ $rc != 0 ]; then
    say "the $1 tests did not run: its Triton kernels are kept, untested here"
  fi
}
if [ "$DEVICE" != cpu ]; then
  triton_tests Fisher tests-triton.txt tests/nbv/kernels/test_gpu_kernel.py AGILEGS_KERNELS torch
  triton_tests "anchor's ψ" tests-triton-anchor.txt tests/nbv/kernels/test_gpu_proxy.py \
    AGILEGS_GPU_ANCHOR 0
fi

# 3. selection latency at the first size while gsplat builds (no gsplat involved), with the slow
#    variants
first_n=${LATENCY_SIZES%% *}
latency() {  # n methods limit [name shape...]
  local n=$1 methods=$2 limit=$3 name=${4:-$1}
  shift 4 2>/dev/null || shift 3
  timeout "$limit" $AG bench latency --device "$DEVICE" ${*:-$LATENCY} --max-gaussians "$n" \
    --methods "$methods" --json "$OUT/latency-$name.json" >"$OUT/logs/latency-$name.txt" 2>&1
  say "bench latency $name: exit $?"
}
latency "$first_n" "$LATENCY_METHODS${LATENCY_SLOW:+,$LATENCY_SLOW}" $((DEADLINE / 7))

# wait for the build, at most until LATE seconds
LATE=${LATE:-$((DEADLINE / 4))}
while kill -0 $BUILD 2>/dev/null && [ "$(elapsed)" -lt "$LATE" ]; do sleep 2; done
kill $BUILD 2>/dev/null && say "gsplat build stopped (too slow)"
RAST=auto
if grep -q "exit 0" "$OUT/logs/gsplat-build.txt"; then
  [ -n "${GSPLAT_SITE:-}" ] && export PYTHONPATH="$GSPLAT_SITE${PYTHONPATH:+:$PYTHONPATH}"
else
  RAST=builtin
  say "no gsplat: training uses the builtin rasterizer"
fi
say "$(tail -1 "$OUT/logs/gsplat-build.txt")"

# 4. the protocol: one process per (scene, method), all at once on the one GPU; RESERVE seconds
#    are kept for the timings after it (alone on the GPU)
RESERVE=${RESERVE:-$((DEADLINE * 2 / 5))}
[ "$DEVICE" = cpu ] && TESTS=""
RUN_S=$(( $(left) - RESERVE - 20 ))
say "bench run: $RUN_S s for each run"
SCENES="$SCENE_OBJECT:$OBJECT_RES $SCENE_CAPTURE:$CAPTURE_RES"
for scene in $SCENES; do
  path=${scene%%:*}; res=${scene##*:}; name=$(basename "$path")
  for m in $METHODS; do
    OMP_NUM_THREADS=1 timeout "$RUN_S" $AG bench run --scene "$path" --profile "$PROFILE" \
      $SHORT --resolution "$res" --rasterizer $RAST --seeds "$SEEDS" --device "$DEVICE" \
      --methods "$m" --no-plots --out "$OUT/run-$name" >"$OUT/logs/run-$name-$m.txt" 2>&1 &
  done
done
wait
for scene in $SCENES; do
  path=${scene%%:*}; res=${scene##*:}; name=$(basename "$path")
  $AG bench run --scene "$path" --profile "$PROFILE" $SHORT --resolution "$res" \
    --rasterizer $RAST --seeds "$SEEDS" --device "$DEVICE" --methods "$(echo $METHODS | tr ' ' ,)" \
    --out "$OUT/run-$name" --report-only >"$OUT/logs/report-$name.txt" 2>&1
  say "bench run $name: exit $?"
done

# 5. the timings, alone on the GPU: latency at the other sizes, the CUDA tests, bench render
last_n=$first_n
for n in ${LATENCY_SIZES#"$first_n"}; do
  latency "$n" "$LATENCY_METHODS" $(( $(left) * 2 / 5 ))
  last_n=$n
done
if [ -n "$LATENCY_WIDE" ]; then  # the largest size again at the wide image
  latency "$last_n" "$LATENCY_METHODS" $(( $(left) / 3 )) "$last_n-wide" $LATENCY_WIDE
fi
if [ "$DEVICE" != cpu ]; then
  # the other CUDA tests (TESTS: the maths', gsplat's; the server's need the whole service
  # extra, as a full install has it)
  if [ -n "$TESTS" ]; then
    timeout "$TESTS_S" "$PY" -m pytest -q -p no:cacheprovider -m cuda -rA $TESTS \
      >"$OUT/logs/tests.txt" 2>&1
    say "CUDA tests: exit $? ($(tail -1 "$OUT/logs/tests.txt"))"
  fi
fi
timeout $(( $(left) - 5 )) $AG bench render --device "$DEVICE" $RENDER --scene "$OBJECT_SPLAT" \
  --json "$OUT/render.json" >"$OUT/logs/render.txt" 2>&1
say "bench render: exit $?"

say "done"
for f in "$OUT"/logs/latency-*.txt "$OUT/logs/render.txt" "$OUT"/run-*/table.md; do
  [ -f "$f" ] && { echo "== $f"; tail -40 "$f"; }
done
exit 0
