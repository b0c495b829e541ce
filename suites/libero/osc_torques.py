"""One arm's OSC_POSE torques for one physics substep, in one compiled call.

robosuite's `OperationalSpaceController.update` + `run_controller` + the robot's clip, for the
settings `fast_step.supported()` accepts, written as the same numpy operations in the same order
and compiled by robosuite's own `jit_decorator` (numba, as robosuite compiles its
`opspace_matrices`, `nullspace_torques` and `orientation_error`, which this calls). numba's
elementwise arithmetic is IEEE's, as numpy's is, and its `np.dot` calls the same BLAS kernel per
memory layout as numpy's, so the torques are robosuite's to the bit
(tests/test_libero_fast_step.py compares whole trajectories for exact equality). One call
instead of some twenty-five numpy calls from Python takes a third off the controller's time per
substep (docs/performance.md). With robosuite's numba turned off it is the same function in
Python.
"""

from __future__ import annotations

import numpy as np
from robosuite.utils.control_utils import nullspace_torques, opspace_matrices, orientation_error
from robosuite.utils.numba import jit_decorator

STEP_ROWS = 10  # an arm's `step` array: the rows step_values fills and osc_torques reads


def step_values(step: np.ndarray, osc, origin_pos: np.ndarray, origin_ori: np.ndarray,
                base_vel: tuple | None = None) -> None:
    """What run_controller recomputes per substep from values that are constant within a control
    step on a fixed base, as it computes them: the goal in the world (rows 0-3), the gains'
    position and orientation halves (4-7) and the base's velocity (8-9; zero for a fixed base,
    as np.dot(its all-zero Jacobian, qvel))."""
    step[0] = origin_pos + np.dot(origin_ori, osc.goal_pos)
    step[1:4] = np.dot(origin_ori, osc.goal_ori)
    step[4], step[5], step[6], step[7] = osc.kp[0:3], osc.kp[3:6], osc.kd[0:3], osc.kd[3:6]
    if base_vel is not None:
        step[8], step[9] = base_vel


@jit_decorator
def osc_torques(jacp, jacr, qvel, dofs, qM, mass_t, J_full, J_pos, J_ori, step, ref_pos, ref_ori,
                bias, initial_joint, joint_pos, joint_vel, low, high, ctrl, actuators,
                mass, torques, ref_vel):
    """Write the arm's clipped torques into `ctrl[actuators]`.

    `jacp`, `jacr`: mj_jacSite's [3, nv] at the end-effector site, just computed; `dofs`: the
    arm's dof addresses; `mass_t`: the addresses of the arm's inertia block in `qM`, transposed;
    `J_full` [6, n] (C order) with its halves `J_pos`, `J_ori` as views; `step`: the goal in the
    world, the gains' halves and the base's velocity (`step_values`). Leaves robosuite's state in
    `mass` (the block, transposed: `mass.T` is robosuite's Fortran-ordered mass matrix),
    `torques` (before the clip) and `ref_vel` (the site's linear and angular velocity)."""
    # Controller.update: the site's velocities, the Jacobian's columns, the inertia block
    ref_pos_vel = np.dot(jacp, qvel)
    ref_ori_vel = np.dot(jacr, qvel)
    n = dofs.shape[0]
    for i in range(3):
        for j in range(n):
            J_pos[i, j] = jacp[i, dofs[j]]
            J_ori[i, j] = jacr[i, dofs[j]]
    for i in range(n):
        for j in range(n):
            mass[i, j] = qM[mass_t[i, j]]
    mass_matrix = mass.T  # Fortran order, as robosuite's fancy indexing of mj_fullM leaves it
    ref_vel[0] = ref_pos_vel
    ref_vel[1] = ref_ori_vel

    # run_controller, for the fixed impedance and decoupled position and orientation
    ori_error = orientation_error(step[1:4], ref_ori)
    position_error = step[0] - ref_pos
    vel_pos_error = -(ref_pos_vel - step[8])
    desired_force = np.multiply(position_error, step[4]) + np.multiply(vel_pos_error, step[6])
    vel_ori_error = -(ref_ori_vel - step[9])
    desired_torque = np.multiply(ori_error, step[5]) + np.multiply(vel_ori_error, step[7])
    _, lambda_pos, lambda_ori, nullspace_matrix = opspace_matrices(mass_matrix, J_full, J_pos,
                                                                   J_ori)
    decoupled_wrench = np.concatenate((np.dot(lambda_pos, desired_force),
                                       np.dot(lambda_ori, desired_torque)))
    torques[:] = np.dot(J_full.T, decoupled_wrench) + bias
    torques += nullspace_torques(mass_matrix, nullspace_matrix, initial_joint, joint_pos,
                                 joint_vel)
    # the robot's clip to the actuators' range (np.clip's ufunc loop is max-then-min)
    clipped = np.minimum(np.maximum(torques, low), high)
    for k in range(n):
        ctrl[actuators[k]] = clipped[k]
