"""Batched simulation of the vabench dual-arm robot: C MuJoCo, MuJoCo Warp (`sim_mjx.warp`)
and MJX on JAX behind one interface (`interface.BatchBase`), chosen in `backends`.

    scene, robot_constants, variants   the scene and its object variants, as MuJoCo models
    kinematics, controller, layout     closed-form FK/IK, the fixed executor, the arms' layout
    actions                            model-facing actions as command rows
    interface, backends                the batch interface, and the one place a backend is chosen
    cpu, mjx_batch, warp/              the three backends
    reset_cache                        settled initial states on disk
    jax_setup                          JAX's configuration, imported by the modules that use it

Nothing is imported here.
"""
