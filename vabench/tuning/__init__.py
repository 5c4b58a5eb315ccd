"""GPU and host tuning beneath the sweep: Warp kernels compiled ahead (`precompile`,
`warp_ahead`), engine processes sharing a GPU (`mps`) and the environment every engine process
starts with (`engine_env`), the episodes a process keeps in flight to keep the machine busy
(`inflight`), what the GPU and the host are busy with (`gpu_busy`, `hostload`,
`kernel_profile`). None of it decides what a sweep runs; each module measures, sizes or
prepares the machine the sweep runs on."""
