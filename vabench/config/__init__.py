"""Sweep configuration: the YAML file `python -m vabench.sweep CONFIG` runs.

    name: my-sweep                 # default: the file's stem
    out: runs/my-sweep             # default: runs/<name>
    models:                        # vabench.llm_pool.config.ModelEndpoint entries
      - {name: local, api: openai_chat, base_url: embedded}   # the sweep's embedded server
      - {name: gpt, api: openai_chat, model: gpt-5, api_key_env: OPENAI_API_KEY,
         prices: {input: 1.25, output: 10.0}}
    embedded_server: {policy: random_action}   # vabench.llm_pool.server.ServerConfig fields
    tracks: [active, passive]      # built-in: active, passive (base suite), transfer (the held-out
                                   # variants of the selected tasks), long_horizon (the basket);
                                   # or {name, protocol, suite, summaries} for an ablation track
    summaries: own                 # every track's default: own | none | shared:<model>
    learning: {demo_cache: null, max_model_calls: 20}  # null: ~/.cache/vabench/demos
    tasks: base                    # the 14 base families, or a list of registered task names
    seeds: verified                # each task's manifest; {verified: N}: its first N; [1000, 1001]:
                                   # these seeds for every task; {task: [seeds]}: per task
    runs: 3
    step_budget: 5                 # optional cap on every task's budget (smoke runs)
    simulator: {backend: auto, lanes: null, window_s: 0.01}  # backend: auto | warp | mjx | c
    render: {backend: auto, width: 1280, height: 960, quality: 95, subsampling: "420",
             workers: 2, platform: auto}   # backend: auto | warp (GPU) | gl
    executor: {kind: auto, address: null, actors: null, max_tasks: null, max_episodes: 256,
               in_flight: auto, slots_per_task: null}  # kind: auto | local | processes | ray
    retries: {infrastructure_rounds: 3}
    profiling: {hostload_s: 60}    # what the sweep measures of itself (profiles, "host:" lines)

The fields a `VABENCH_*` variable overrides (`simulator.warp_loop`, `render.warp_jpeg`, ...) are
listed by `vabench.switches`; `load_config` gives them the environment's values where set.

`load_config` reads and checks the whole file before anything is called: unknown keys (typos),
wrong types, bad ranges, unknown tasks (with a "did you mean"), unusable seed specs, missing
seed manifests, unset API-key variables, duplicate or path-unsafe model names and unknown
embedded-server policies. Every problem found becomes one line of a single `SweepConfigError`,
`<file>: <dotted field>: <problem>`, so one edit round fixes them all.

Tracks: a track is a camera protocol, a task suite and a summary mode. `active` and `passive`
run the selected `tasks`; `transfer` runs the held-out variants (`<base>_heldout`) of the
selected base families; `long_horizon` runs the basket task. Every track reads summaries learned
from demonstrations (vabench.agent.learning_stage): `own` (the model's own, learned once per family
in a learning stage), `shared:<model>` (another model's) or `none`. A custom track such as
`{name: active_none, protocol: active, summaries: none}` runs a summary-source ablation next to
`active` in the same sweep.

The result, `SweepConfig`, is resolved: explicit tracks, task names and the seeds of each task.
`SweepConfig.document()` is a YAML-able mapping of that resolved config (what the sweep writes
to RUN_DIR/sweep.yaml) which `load_config` reads back to an equal config.

Modules: `schema` (the sections and `SweepConfig`), `load` (reading the file), `resolve` (the
checks pydantic cannot make; tracks, tasks and seeds), `problems` (errors naming the field),
`overrides` (the command line's quick-trial flags, applied to the document before it is
checked), `choices` (every `auto` of a config resolved for this machine, once, as `Choices`).
"""

from vabench.config.load import load_config
from vabench.config.problems import Problem, SweepConfigError
from vabench.config.schema import (
    BUILTIN_TRACKS,
    EMBEDDED,
    EMBEDDED_PLACEHOLDER_URL,
    SUMMARY_MODES,
    TRACKS,
    ExecutorOptions,
    LearningOptions,
    ProfilingOptions,
    RenderOptions,
    RetryOptions,
    SimulatorOptions,
    Suite,
    SweepConfig,
    Track,
    TrackSpec,
    suite_tasks,
)

__all__ = [
    "BUILTIN_TRACKS",
    "EMBEDDED",
    "EMBEDDED_PLACEHOLDER_URL",
    "SUMMARY_MODES",
    "TRACKS",
    "ExecutorOptions",
    "LearningOptions",
    "Problem",
    "ProfilingOptions",
    "RenderOptions",
    "RetryOptions",
    "SimulatorOptions",
    "Suite",
    "SweepConfig",
    "SweepConfigError",
    "Track",
    "TrackSpec",
    "load_config",
    "suite_tasks",
]
