"""Hand-written reverse kernels (thesis eq 41-71): one reverse twin per forward function of mls_mpm's step.

A forward function `mls_mpm.<module>.<name>` has its twin `adjoint.<module>.<name>_reverse`, with the same
arguments plus the adjoint state `a` where it needs one. TWINS lists each pair with the thesis equations the
twin implements; NO_TWIN lists the forward functions that have none, and why. tests/test_twins.py checks that
the two tables cover every forward function of the step's modules and that tests/test_adjoint_kernels.py
exercises every twin.
"""

# module -> {forward function: thesis equations of its reverse twin (forward name + "_reverse")}
TWINS = {
    "transfer": {
        "p2g_particle": "eq 54-65, 71",
        "g2p_particle": "eq 47-48, 57, 66-69",
        "p2g_slab": "eq 59-65 on one slab of the stencil (inside p2g_particle_reverse)",
        "g2p_slab": "eq 48, 66-69 on one slab of the stencil (inside g2p_particle_reverse)",
        "p2g": "eq 54-65, 71",
        "g2p": "eq 47-48, 57, 66-69",
        "check_particle": "a non-finite adjoint (no equation)",
        "record_fault": "a non-finite adjoint (no equation)",
    },
    "grid": {
        "grid_op_node": "eq 49-53",
        "grid_op": "eq 49-53",
    },
    "material": {
        "stress": "eq 57 (second term)",
        "rotated_stress": "eq 57 (second term), R given",
    },
    "losses": {
        "splat": "eq 42-43",
        "grid_loss": "eq 41, 72",
        "ot_loss": "dS/dm_i from the Sinkhorn potentials (mls_mpm/ot.py), in place of eq 41",
        "position_loss": "eq 10",
        "evaluate": "eq 41-46",
    },
    "step": {
        "gather_lanes": "sum of the private grids of dL/dv_i",
        "grid_node": "eq 49-53",
        "step_loops": "eq 47-71",
        "substep": "eq 47-71",
        "run_parallel": "eq 47-71",
        "run_serial": "eq 47-71",
    },
    "persistent": {
        "run_persistent": "eq 47-71, the parallel schedule's reverse loops in one launch",
        "persistent_pass": "eq 47-71 (run_persistent_reverse; whether it finished)",
    },
}

# module -> {forward function without a twin: why}
NO_TWIN = {
    "transfer": {
        "control_sum": "F + F_pc is linear: adjoint.step.particle_adjoint adds dL/dF_p to dL/dF_pc (eq 55)",
        "affine_momentum": "differentiated inline by p2g_particle_reverse (eq 54, 57-58)",
        "particle_G": "differentiated inline by p2g_particle_reverse (eq 54, 57-58, 61)",
        "scatter_node": "its reverse is the gather of dL/dm_i, dL/dp_i inside p2g_particle_reverse (eq 59-65)",
        "check_step": "the check of the last step; the reverse checks every step in step_loops_reverse",
    },
    "grid": {
        "wall_mask": "piecewise constant: grid_op_node_reverse applies the same mask (eq 50)",
        "free_velocity": "differentiated inline by grid_op_node_reverse (eq 50-53)",
        "velocity_slot": "an index into s.grid_v, no value to differentiate",
    },
    "material": {
        "cofactor": "differentiated by adjoint.material.cofactor_adjoint (2D: linear, cofactor itself; 3D: bilinear)",
        "polar_rotation": "differentiated in closed form by adjoint.material.rotation_adjoint (2D dR/dtheta, 3D R [omega])",
        "svd_rotation": "polar_rotation's starting guess: its Newton steps make dR independent of it",
        "higham_rotation": "polar_rotation for a well-conditioned F: rotation_adjoint differentiates the converged R",
        "higham_step": "one step of higham_rotation: rotation_adjoint differentiates the converged R",
        "inverse_cbrt": "higham_step's scaling |det X|^(-1/3): rotation_adjoint differentiates the converged R",
        "higham_steps": "an integer step count for higham_rotation: nothing to differentiate",
        "higham_fewer": "a compile-time step count by float type (Python): nothing to differentiate",
        "newton_rotation": "polar_rotation's Newton step: rotation_adjoint differentiates the converged R",
        "jacobi_rotate": "part of svd_rotation's starting guess (no derivative needed)",
        "sort_columns": "part of svd_rotation's starting guess (no derivative needed)",
        "unit_or": "part of svd_rotation's starting guess (no derivative needed)",
        "rotation_solve": "linear in h: rotation_adjoint calls it again with the adjoint (M is symmetric)",
        "cayley": "polar_rotation's Newton update; rotation_adjoint uses its first order, I + [omega]_x",
        "cross_matrix": "linear: rotation_adjoint applies it to the adjoint",
        "axial": "linear: rotation_adjoint applies it to the adjoint",
    },
    "losses": {
        "splat_value": "constant in x: splat_reverse reads it",
        "node_residual": "differentiated inline by grid_loss_reverse (eq 41; log mass: 1 / (m_i + 1))",
        "node_penalty": "constant: grid_loss_reverse reads it (eq 72)",
        "seed_loss": "the Tape's linear stand-in for ot_loss: its derivative is the seed that ot_loss_reverse reads",
    },
    "persistent": {
        "barrier": "synchronisation of the lanes' threads: the reverse pass uses the same barrier",
        "tick": "the lanes' progress for the barrier: the reverse pass ticks it too",
        "work_done": "the lanes' progress read by the barrier, which the reverse pass uses too",
        "chunks": "an index range cut in chunks (the reverse pass cuts its loops alike)",
        "chunk": "an index range cut in chunks (the reverse pass cuts its loops alike)",
        "own_nodes": "an index range (the reverse pass takes the same share)",
        "own_particles": "an index range (the reverse pass takes the same share)",
        "lane_shares": "index ranges (the reverse pass takes the same shares)",
        "joined_box": "the nodes the grid loop visits (integers); the reverse pass reads the stored box",
    },
    "active": {
        "empty_box": "integer node bounds: nothing to differentiate",
        "widen": "integer node bounds of a particle's stencil: nothing to differentiate",
        "store_box": "integer node bounds: nothing to differentiate",
        "load_box": "integer node bounds, which the reverse pass reads too",
        "merge_box": "integer node bounds: nothing to differentiate",
        "reverse_box": "integer node bounds used by the reverse pass itself",
        "volume": "an index count (the reverse pass's grid loop uses it too)",
        "node_in": "an index conversion (the reverse pass uses it too)",
    },
    "step": {
        "clear_node": "zeroes an accumulator: the reverse zeroes its adjoints where it consumes them",
        "clear_grid": "zeroes an accumulator: adjoint.state.zero_step zeroes the adjoints before a reverse pass",
    },
}
