#!/usr/bin/env bash
# One phase of the GPU measurements on the lent device machine; each phase fits one call
# (< 10 minutes) and writes its results under $OUT. The order of calls (device tool):
#   1. carry .wp1 .ray1:  mkdir -p /tmp/wp /tmp/ray && cp .wp1/* /tmp/wp/ && cp .ray1/* /tmp/ray/
#   2. carry .wp2 .ray2 .spy:  mkdir -p /tmp/wp /tmp/ray /tmp/spy && cp .wp2/* /tmp/wp/ &&
#      cp .ray2/* /tmp/ray/ && cp .spy/* /tmp/spy/   (.spy: the py-spy wheel, for MAIN_PYSPY)
#      (a call carries 64 MiB with the ~4.5 MiB tree: .wp1 45 + .ray1 13.4, .wp2 45 + .ray2 7.6
#      + .spy 2.8, .wp3 7.5 + .whl 40.3 + .gl 0.4 + .nvj 5.8 + .ray3 4.0 MiB, measured 2026-11-27)
#      (the image had aiohttp, rich, yaml, PIL and pytest on 2026-11-25; if `setup` says one is
#      missing, carry .dep too and `mkdir -p /tmp/dep && cp .dep/* /tmp/dep/`)
#   3. carry .wp3 .whl .gl .nvj .ray3:  bash benchmarks/gpu/run.sh setup
#   4.. (warm machine, nothing carried):
#        bash benchmarks/gpu/run.sh waits | physics | critical_path | render | render_options | jpeg | jpeg_kernels |
#        fidelity | tests | engine | engine_processes | main | ray |
#        streams |
#        precompile (first on a fresh machine: Warp kernels of every family, in parallel)
#        precompile_bench (vabench/tuning/precompile.py's single phase
#        against its two phases, each from an empty Warp cache; PRECOMPILE_FAMILIES=a,b,c)
# .whl .wp1 .wp2 .wp3 .gl come from ../shared/device/make_parts.sh, .nvj from
# benchmarks/gpu/make_jpeg_part.sh, .dep from benchmarks/gpu/make_deps_part.sh, .ray1-3 (Ray
# for the `ray` phase, optional) from benchmarks/gpu/make_ray_part.sh (all run once here, from
# the project root). `main` runs configs/all.yaml as shipped; a call that ends before
# the sweep does leaves it to the next `main` call, which resumes it (wall times add up).
set -uo pipefail
phase=${1:?usage: run.sh setup|waits|physics|critical_path|render|render_options|jpeg|jpeg_kernels|fidelity|tests|engine|engine_processes|main|ray|streams|precompile|precompile_bench}
out=${OUT:-/tmp/out}
mkdir -p "$out"
export PYTHONPATH=/tmp/site:$PWD PYTHONUNBUFFERED=1 MUJOCO_GL=egl PYOPENGL_PLATFORM=egl
export __EGL_VENDOR_LIBRARY_FILENAMES=/usr/local/nvidia/share/glvnd/egl_vendor.d/10_nvidia.json
export LD_LIBRARY_PATH=/tmp/site/nvidia/cu13/lib:${LD_LIBRARY_PATH:-}
export XLA_PYTHON_CLIENT_PREALLOCATE=false  # JAX shares the card with Warp
export VABENCH_STATE_CACHE=/tmp/settled
date -u +"%Y-%m-%d %H:%M UTC" > "$out/date.txt"
case "$phase" in
  setup)
    # shellcheck disable=SC1091
    source .wp3/gpu_env.sh || exit 1
    tar -xJf .nvj/nvj.tar.xz -C /tmp/site && python3 -m pip install -q --no-index --no-deps \
      --no-compile --target /tmp/site .nvj/*.whl || exit 1
    if ! python3 -c "import aiohttp, rich, yaml, PIL, pytest" 2>/dev/null; then
      ls /tmp/dep/*.whl >/dev/null 2>&1 || { echo "setup: the image lacks aiohttp, rich, yaml, PIL or pytest: carry .dep (see the top of run.sh)"; exit 1; }
      python3 -m pip install -q --no-index --no-deps --no-compile --target /tmp/site /tmp/dep/*.whl \
        || exit 1
    fi
    if ls /tmp/spy/*.whl >/dev/null 2>&1; then
      # a folder of its own: into /tmp/site, pip left the binary out ("Target directory
      # /tmp/site/bin already exists", 2026-11-27), and --upgrade would replace that folder
      python3 -m pip install -q --no-index --no-deps --no-compile --target /tmp/spysite \
        /tmp/spy/*.whl || exit 1
      [ -x /tmp/spysite/bin/py-spy ] || { echo "setup: py-spy did not install"; exit 1; }
    fi
    if [ -d .ray3 ] && ls /tmp/ray/rp.* >/dev/null 2>&1; then
      cat /tmp/ray/rp.* .ray3/rp.* | tar -xJf - -C /tmp/site || exit 1
    fi
    # Python's bytecode, as `pip install` writes it (the parts install with --no-compile): without
    # it a fresh machine's first sweep compiled every module's bytecode in each of its 22
    # precompile children at once, a measuring artefact no user has. Suspected, unproven: the
    # first precompile of a process ran 1.7-2.3x slower than the second (57-79 s against
    # 33-35 s, H200). SETUP_BYTECODE=0 leaves it out.
    if [ "${SETUP_BYTECODE:-1}" != 0 ]; then
      t0=$(date +%s); python3 -m compileall -q -j 0 /tmp/site "$PWD/vabench" >/dev/null 2>&1
      echo "setup: bytecode compiled in $(($(date +%s) - t0)) s"
    fi
    nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv | tee "$out/gpu.txt"
    python3 - <<'PY' 2>&1 | tee "$out/setup.log"
import mujoco, mujoco_warp, warp as wp, simplejpeg
from nvidia import nvimgcodec
print("mujoco", mujoco.__version__, "mujoco_warp", mujoco_warp.__version__, "warp", wp.__version__)
print("nvimgcodec", nvimgcodec.__version__, nvimgcodec.Encoder(device_id=0))
from vabench.render.backends import resolve_renderer
from vabench.sim_mjx.backends import resolve
print(resolve("auto"), resolve_renderer("auto"))
PY
    ;;
  waits)
    # How much of a core a thread waiting for the GPU takes: Warp's events, ours (blocking
    # sync), a stream synchronisation (the engine threads' 0.3-0.9 cores a process)
    timeout 120 python3 benchmarks/gpu_waits.py 2>&1 | tee "$out/waits.log"
    ;;
  physics)
    timeout 570 python3 benchmarks/sim_throughput.py --sizes 256,1024,8192 --backends warp,c \
      --loops per_step --budget-s 300 --json "$out/sim.json" 2>&1 | tee "$out/sim.log"
    ;;
  render)
    timeout 570 python3 benchmarks/render_throughput.py --sizes 640x480,1280x960 \
      --batches 1,256,1024 --workers 8 --slots 256 --repeats 10 \
      --json "$out/render.json" 2>&1 | tee "$out/render.log"
    ;;
  fidelity)
    # FIDELITY_ACTION_END=at_rest|paced: the guard of simulator.action_end at_rest or paced
    timeout "${FIDELITY_TIMEOUT_S:-570}" python3 benchmarks/warp_fidelity.py --tasks "${FIDELITY_TASKS:-all}" --n 20 --budget-s "${FIDELITY_BUDGET_S:-420}" \
      --action-end "${FIDELITY_ACTION_END:-fixed}" \
      --json "$out/fidelity.json" --md "$out/fidelity.md" 2>&1 | tee "$out/fidelity.log"
    ;;
  critical_path)
    # The basket's decision physics at 15/30/60 worlds, today's action length against
    # simulator.action_end at_rest and paced (CRITICAL_VARIANTS picks; its Warp modules
    # compiled in threads first)
    timeout "${CRITICAL_TIMEOUT_S:-300}" python3 benchmarks/critical_path.py \
      --sizes "${CRITICAL_SIZES:-15,30,60}" --actions "${CRITICAL_ACTIONS:-12}" \
      --variants "${CRITICAL_VARIANTS:-fixed,at_rest,paced}" \
      --json "$out/critical_path.json" 2>&1 | tee "$out/critical_path.log"
    ;;
  tests)
    timeout 570 python3 -m pytest -q -x -p no:cacheprovider tests/test_warp_batch.py \
      tests/test_render_warp.py tests/test_cuda_sync.py 2>&1 | tee "$out/tests.log"
    timeout 200 python3 benchmarks/warp_gpu_checks.py --json "$out/checks.json" 2>&1 \
      | tee "$out/checks.log"
    ;;
  engine)
    # The engine's and the server's figures: episodes in flight against the ideal C/L (Warp
    # physics + Warp images, the model served by 4 processes of its own, then C MuJoCo + GL as
    # the CPU path's figure on the same host), and the embedded server's calls/s against its
    # policy worker processes and its serving processes.
    timeout 300 python3 benchmarks/engine.py --backend warp --renderer warp \
      --concurrency 1,100,1000,2000 --latency 2 --steps 5 --size 640x480 --server-processes 4 \
      --json "$out/engine_warp.json" 2>&1 | tee "$out/engine.log"
    timeout 120 python3 benchmarks/engine.py --backend c --renderer gl --render-workers 8 \
      --concurrency 1000 --latency 2 --steps 5 --size 640x480 \
      --json "$out/engine_c.json" 2>&1 | tee -a "$out/engine.log"
    timeout 200 python3 benchmarks/server_scaling.py --processes 0,8 --server-processes 4,8,15 \
      --concurrency 64 --seconds 15 --json "$out/server.json" 2>&1 | tee "$out/server.log"
    ;;
  engine_processes)
    # The engine's rounds over 8 engine processes under MPS, as the sweep runs them (one process
    # is bounded by its CPU, ~2.5 ms a decision; measured: 0.78 at C = 1,000 and
    # 0.71 at C = 2,000 with 8), at the simulator's default window and at 0.1 s (one process at
    # C = 1,000: 0.49 -> 0.58). A one-process row first: on a fresh host it compiles the scene's
    # kernels once (~80 s), not in each of the 8 processes side by side.
    timeout 560 python3 benchmarks/engine.py --backend warp --renderer warp \
      --sim-window 0.01,0.1 --concurrency 1000,2000 --processes 1,8 --latency 2 --steps 5 \
      --size 640x480 --server-processes 4 --json "$out/engine_processes.json" 2>&1 \
      | tee "$out/engine_processes.log"
    ;;
  main)
    # The product's front door as shipped, timed; the report is made from results.jsonl
    # afterwards (matplotlib is not on the device image).
    # MAIN_EXECUTOR=local|processes|ray (and MAIN_MAX_TASKS=n, MAIN_MAX_EPISODES=n) times
    # another layout of the same plan (a copy of the config with only the executor changed); a
    # run directory per layout (MAIN_RUN_DIR names another). Another commit's tree (`git
    # archive COMMIT vabench benchmarks configs assets pyproject.toml` into an ignored folder,
    # carried) runs from that folder: `cd FOLDER && bash ../benchmarks/gpu/run.sh main`.
    # MAIN_ACTION_END=at_rest|paced: the same plan with that simulator.action_end
    layout=${MAIN_EXECUTOR:-}${MAIN_MAX_EPISODES:+_$MAIN_MAX_EPISODES}${MAIN_ACTION_END:+_$MAIN_ACTION_END}
    run=${MAIN_RUN_DIR:-/tmp/run_all${layout:+_$layout}}
    config=configs/all.yaml
    if [ -n "$layout" ]; then
      config=/tmp/all_$layout.yaml
      python3 -c "import sys, yaml; d = yaml.safe_load(open('configs/all.yaml'));
kind, n, e, end = sys.argv[1], int(sys.argv[3]), int(sys.argv[4]), sys.argv[5];
d['executor'] = {**(d.get('executor') or {})} | ({'kind': kind} if kind else {}) | ({'max_tasks': n} if n else {}) | ({'max_episodes': e} if e else {});
d['simulator'] = {**(d.get('simulator') or {})} | ({'action_end': end} if end else {});
yaml.safe_dump(d, open(sys.argv[2], 'w'))" "${MAIN_EXECUTOR:-}" "$config" "${MAIN_MAX_TASKS:-0}" \
        "${MAIN_MAX_EPISODES:-0}" "${MAIN_ACTION_END:-}" || exit 1
    fi
    # A run directory keeps every image the models saw (~20-30 GB for configs/all.yaml): the
    # third run on one 64 GiB host filled its disk and the machine stopped answering
    # (2026-11-27). Earlier calls' run directories go (each named as it was run, and only
    # where it holds a run's episodes/), except the one this call resumes.
    run=$(realpath -m "$run")
    touch /tmp/main_runs.txt
    while read -r old; do
      if [ -n "$old" ] && [ "$old" != "$run" ] && [ -d "$old/episodes" ]; then
        echo "main: removing an earlier call's run directory $old (disk space)" | tee -a "$out/main_disk.txt"
        rm -rf "$old"
      fi
    done < /tmp/main_runs.txt
    grep -qx "$run" /tmp/main_runs.txt || echo "$run" >> /tmp/main_runs.txt
    df -h /tmp | tail -1 | tee -a "$out/main_disk.txt"
    python3 -m vabench.sweep "$config" --dry-run 2>&1 | tail -8 | tee "$out/main_choices.txt"
    # MAIN_PROFILE=1: each worker writes a cProfile of its chunks (summed into main_profile.txt);
    # always: GPU and CPU use every 5 s (main_util.txt: time, GPU %, GPU MiB, /proc/stat cpu)
    [ -n "${MAIN_PROFILE:-}" ] && export VABENCH_PROFILE_DIR=/tmp/prof && rm -rf /tmp/prof
    (while :; do echo "$(date +%s) $(nvidia-smi --query-gpu=utilization.gpu,memory.used \
      --format=csv,noheader,nounits | tr '\n' ' ') $(head -1 /proc/stat)"; sleep "${MAIN_SAMPLE_S:-2}"; done \
      > "$out/main_util.txt") &
    sampler=$!
    # MAIN_PYSPY=1: py-spy samples the sweep process and its children (every thread, idle ones
    # too: where they wait is the point) for MAIN_PYSPY_S seconds from MAIN_PYSPY_AT s after the
    # start, as collapsed stacks (benchmarks/profile_summary.py reads them), plus dumps with
    # native frames (what a thread waits for inside a C extension: a CUDA sync, a mutex, the
    # interpreter's lock) at MAIN_PYSPY_DUMPS seconds after the start (default: 30, 60 and 90
    # s after MAIN_PYSPY_AT). A dump stops each process while it unwinds (a second or more):
    # a run with dumps is not a timing run.
    # MAIN_PYSPY=gil: only the thread holding the interpreter lock, each sample (what paces a
    # process whose event loop waits for the lock: the "host:" lines tell when).
    # Always: the sweep's "host:" lines every 15 s (vabench/tuning/hostload.py).
    export VABENCH_HOSTLOAD_S=${VABENCH_HOSTLOAD_S:-15}
    spy_mode="--idle"
    [ "${MAIN_PYSPY:-}" = gil ] && spy_mode="--gil"
    if [ -n "${MAIN_PYSPY:-}" ]; then
      at=${MAIN_PYSPY_AT:-40}
      for t in ${MAIN_PYSPY_DUMPS:-$((at + 30)) $((at + 60)) $((at + 90))}; do
        (sleep "$t"; pid=$(pgrep -of "^python3 -m vabench.sweep $config --out") || exit 0
         { echo "=== dump at ${t} s"; /tmp/spysite/bin/py-spy dump --pid "$pid" --subprocesses \
           --native; } >> "$out/pyspy_dump.txt" 2>&1) &
      done
      (sleep "$at"; pid=$(pgrep -of "^python3 -m vabench.sweep $config --out") || exit 0
       /tmp/spysite/bin/py-spy record --pid "$pid" --subprocesses --threads $spy_mode --rate 20 \
         --nonblocking --format raw --duration "${MAIN_PYSPY_S:-120}" -o "$out/pyspy.raw" \
         > "$out/pyspy.log" 2>&1) &
    fi
    # MAIN_MPS=1: CUDA's multi-process service for the run, so that the kernels of several
    # engine processes (MAIN_EXECUTOR=processes MAIN_MAX_TASKS=n) run side by side on the GPU
    # instead of their contexts taking turns (the test of one process being bound by Python's
    # interpreter lock: the "host:" lines).
    if [ -n "${MAIN_MPS:-}" ]; then
      if command -v nvidia-cuda-mps-control >/dev/null; then
        export CUDA_MPS_PIPE_DIRECTORY=/tmp/mps_pipe CUDA_MPS_LOG_DIRECTORY=/tmp/mps_log
        mkdir -p /tmp/mps_pipe /tmp/mps_log && nvidia-cuda-mps-control -d \
          && echo "MPS on" | tee "$out/main_mps.txt"
      else
        echo "MPS asked for, but nvidia-cuda-mps-control is not on this image" | tee "$out/main_mps.txt"
      fi
    fi
    # A fresh machine's precompile: each family's child's report (modules compiled, waited
    # for, compiled after the first step; each part's seconds) comes back in main_extra.tgz.
    export VABENCH_PRECOMPILE_STATS=$out/precompile_stats
    # MAIN_KERNELS=1: every engine worker records MAIN_KERNELS_S (20) seconds of its GPU
    # kernels from MAIN_KERNELS_AT (60) s after its start (CUPTI through PyTorch, which the
    # image has: vabench/tuning/kernel_profile.py), summed into main_kernels.txt; not a timing run.
    if [ -n "${MAIN_KERNELS:-}" ]; then
      rm -rf /tmp/kern && export VABENCH_KERNEL_PROFILE=/tmp/kern \
        VABENCH_KERNEL_PROFILE_AT=${MAIN_KERNELS_AT:-60} VABENCH_KERNEL_PROFILE_S=${MAIN_KERNELS_S:-20}
    fi
    # MAIN_FRESH=1: a fresh machine's caches again (Warp's kernels, vabench's markers and
    # settled states, JAX's cache) and a new run directory: the fresh A/B on one warm host
    # (e.g. VABENCH_WARP_PRECOMPILE=first against the background compile).
    if [ -n "${MAIN_FRESH:-}" ]; then
      rm -rf "$HOME/.cache/warp" "$HOME/.cache/vabench" "$VABENCH_STATE_CACHE" "$run"
      echo "main: caches cleared (MAIN_FRESH)" | tee -a "$out/main_disk.txt"
    fi
    start=$EPOCHREALTIME
    timeout -s INT "${MAIN_TIMEOUT_S:-520}" python3 -m vabench.sweep "$config" --out "$run" --plain \
      --progress-every 10 --no-report 2>&1 | tee "$out/main.log"
    rc=${PIPESTATUS[0]}
    echo "rc $rc wall_s $(python3 -c "print(round($EPOCHREALTIME - $start, 1))")" | tee -a "$out/main_wall.txt"
    kill $sampler 2>/dev/null
    [ -n "${MAIN_MPS:-}" ] && command -v nvidia-cuda-mps-control >/dev/null \
      && echo quit | nvidia-cuda-mps-control
    grep -a " host" "$out/main.log" > "$out/main_host.txt"
    # where each decision's time went (physics, images, model, engine), per task and over time
    timeout 120 python3 benchmarks/episode_timeline.py "$run" --window 20 \
      --t0 "$(head -1 "$out/main_util.txt" | cut -d' ' -f1)" > "$out/main_timeline.txt" 2>&1
    [ -n "${MAIN_KERNELS:-}" ] && python3 -m vabench.tuning.kernel_profile /tmp/kern \
      > "$out/main_kernels.txt" 2>&1
    if [ -n "${MAIN_PROFILE:-}" ]; then
      python3 -c "import glob, pstats; s = pstats.Stats(*glob.glob('/tmp/prof/*.prof'));
s.sort_stats('tottime').print_stats(40); s.sort_stats('cumtime').print_stats(40)" \
        > "$out/main_profile.txt" 2>&1
    fi
    cp "$run"/results.jsonl "$run"/infrastructure.jsonl "$run"/*.json "$out/" 2>/dev/null
    [ -d "$run/logs" ] && cp -r "$run/logs" "$out/worker_logs"  # the engine workers' own lines
    # ... whose "host:" lines (each loop's lateness beside the machine's runnable threads and
    # the garbage collector's share) go into main_host.txt too, each named by its log
    grep -aH " host" "$run"/logs/*.log >> "$out/main_host.txt" 2>/dev/null
    nvidia-smi --query-gpu=memory.used --format=csv | tee "$out/main_gpu_mem.txt"
    # The device tool returns at most 8 files (a py-spy profile was lost to it on 2026-11-27):
    # all but the main ones go into main_extra.tgz.
    (cd "$out" && extra=$(ls | grep -v -x -E \
      'main.log|main_host.txt|main_util.txt|main_wall.txt|results.jsonl|main_timeline.txt|main_kernels.txt|main_extra.tgz') \
      && [ -n "$extra" ] && tar czf main_extra.tgz $extra && rm -rf $extra)
    ;;
  streams)
    # What a CUDA stream (and a host thread) per task batch gains over one stream per
    # device, with graphs of 1, 10, 50 and 200 substeps (STREAMS_ARGS replaces the defaults).
    timeout "${STREAMS_TIMEOUT_S:-500}" python3 benchmarks/warp_streams.py \
      ${STREAMS_ARGS:---worlds 120 --counts 1,14 --chunks 1,10,50,200} --json "$out/streams.json" \
      2>&1 | tee "$out/streams.log"
    ;;
  precompile)
    # Warp compiles its kernels per scene shape (1-2 min each on a fresh machine, then cached in
    # ~/.cache/warp): one process per base family, spread over the GPUs, all at once.
    # PRECOMPILE_GPUS="1" and PRECOMPILE_CPUS=16-31 keep it beside a measurement on GPU 0.
    read -ra gpus <<< "${PRECOMPILE_GPUS:-$(seq -s ' ' 0 $(($(nvidia-smi -L | wc -l) - 1)))}"
    i=0
    for t in $(python3 -c "from vabench.tasks import base_tasks as b; print(*[t.name for t in b()])"); do
      CUDA_VISIBLE_DEVICES=${gpus[$((i % ${#gpus[@]}))]} JAX_PLATFORMS=cpu timeout "${PRECOMPILE_S:-300}" \
        taskset -c "${PRECOMPILE_CPUS:-0-$(($(nproc) - 1))}" python3 benchmarks/warp_fidelity.py --tasks "$t" --n 1 > "/tmp/precompile_$t.log" 2>&1 &
      i=$((i + 1))
    done
    wait
    echo "precompiled $i families: $(grep -l "solved\|GC" /tmp/precompile_*.log | wc -l) finished"
    ;;
  precompile_bench)
    # Temporary Warp caches: leaves ~/.cache/warp as it was (a fresh machine stays fresh).
    fams=${PRECOMPILE_FAMILIES:-$(python3 -c "from vabench.tasks import base_tasks as b; print(','.join(t.name for t in b()[:8]))")}
    # PRECOMPILE_SCHEMES=critical,new: the critical path first (the basket's child ahead, the
    # others at a lower CPU priority) against all alike (use every family: the cores must be
    # oversubscribed for the priority to matter).
    timeout 560 python3 benchmarks/precompile.py --device cuda:0 --size "${PRECOMPILE_SIZE:-1280x960}" \
      --families "$fams" --schemes "${PRECOMPILE_SCHEMES:-old,new}" --json "$out/precompile.json" \
      2>&1 | grep --line-buffered -av "^Module " | tee "$out/precompile.log"
    ;;
  render_options)
    # The render megakernel's options side by side (GPU ms a pass, pixels changed).
    timeout 560 python3 benchmarks/render_options.py --worlds "${RENDER_WORLDS:-24}" \
      --json "$out/render_options.json" 2>&1 | grep --line-buffered -av "^Module " \
      | tee "$out/render_options.log"
    ;;
  jpeg_kernels)
    # Our JPEG kernels (vabench/render/warp_jpeg.py) alone, `warp_jpeg_check.py`: ms a call,
    # each kernel's GPU time, the bytes against libjpeg-turbo; then in the renderer,
    # `render_throughput.py`'s "warp, jpeg kernels" rows against the GL pool (RENDER_ARGS
    # replaces the sizes, batches and renderers). Warp's "Module ... took" lines stay: the
    # first call's compile time.
    timeout 200 python3 benchmarks/warp_jpeg_check.py --frames 25,128 2>&1 \
      | tee "$out/jpeg_check.log"
    # shellcheck disable=SC2086
    timeout 360 python3 benchmarks/render_throughput.py ${RENDER_ARGS:---sizes 1280x960,640x480 \
      --batches 256,1024 --workers 8 --renderers gl,warp --warp-jpeg kernels --repeats 5} \
      --json "$out/render.json" 2>&1 | grep --line-buffered -av "^Module " | tee "$out/render.log"
    ;;
  jpeg)
    # What a device JPEG call waits for in a busy process (benchmarks/jpeg_contention.py;
    # JPEG_ARGS replaces its defaults).
    timeout 560 python3 benchmarks/jpeg_contention.py ${JPEG_ARGS:-} --json "$out/jpeg.json" \
      2>&1 | grep --line-buffered -av "^Module " | tee "$out/jpeg.log"
    ;;
  ray)
    # The same plan on 1 and 2 (up to RAY_ENGINES) engines, one per GPU, one local
    # Ray instance; RAY_RUNS shrinks the plan (configs/all.yaml has 3 runs).
    # Each count's run directory kept in /tmp/rayruns (removed first: a count of configs/all.yaml
    # writes ~2,160 episodes' frames), then where its decisions spent their time (physics,
    # images, model, per task) into ray_timeline.txt: the chain of the slowest task bounds a
    # count on several GPUs (4 x H200, 2026-11-28). RAY_TIMEOUT_S leaves the timelines time.
    # RAY_ARGS="--per-gpu 4 --dealing budgets,measured": each count dealt by step budgets, then
    # by the seconds an episode of each task took in that run, side by side (RAY_ENGINES=2
    # alone fits one call with configs/all.yaml).
    rm -rf /tmp/rayruns
    timeout "${RAY_TIMEOUT_S:-480}" python3 benchmarks/ray_scaling.py --engines "${RAY_ENGINES:-1,2}" \
      --runs "${RAY_RUNS:-3}" ${RAY_ARGS:-} --json "$out/ray.json" --keep /tmp/rayruns 2>&1 \
      | grep --line-buffered -av "^Module " | tee "$out/ray.log"
    for d in /tmp/rayruns/engines_*; do
      [ -d "$d" ] || continue
      echo "== $(basename "$d")" >> "$out/ray_timeline.txt"
      timeout 30 python3 benchmarks/episode_timeline.py "$d" --window 30 >> "$out/ray_timeline.txt" 2>&1
    done
    ;;
  *) echo "unknown phase $phase"; exit 2 ;;
esac
