"""The MuJoCo Warp backend: every slot of a task family on one GPU (or Warp's CPU device).

    device       which Warp device, whether Warp can run there, the device's lock
    cuda_sync    GPU waits that block instead of spinning a core
    batch        `WarpBatch`, the physics batch (the `BatchBase` interface of `sim_mjx`)
    graphs       how the batch's device work is launched (captured CUDA graphs)
    model        per-world model variants and buffer sizing
    control      the fixed executor's plan and joint references as Warp kernels
    fk_ik        the closed-form kinematics as Warp functions
    arm_indices  the arms' addresses on the device, and the proprioception kernel
    rows         kernels over per-slot rows: the merge, the commit, gathers and scatters

Nothing is imported here: `import vabench.sim_mjx.warp.batch` needs the [gpu] extra, and the
rest of vabench chooses C MuJoCo without loading Warp.
"""
