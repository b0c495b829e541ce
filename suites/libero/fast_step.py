"""`FastStepper`: one LIBERO control step (OSC_POSE at 20 Hz, 25 physics substeps) without
robosuite's per-substep Python, to the same bits.

robosuite's step spends most of its time around the physics, not in it: per substep the OSC
controller re-reads the arm's state through name look-ups and six Jacobian calls, the robot
re-derives its action limits, and every observable (30 of them in a small LIBERO scene) is
visited, though they sample once per control step. This module keeps what determines the
trajectory and drops the rest:

- the OSC torques are computed per substep from cached indices and views of MjData with
  MuJoCo's C functions (`mj_jacSite` once, the arm's block of the inertia read straight from
  `qM`) and one compiled call (`osc_torques`: exactly robosuite's numpy operations on arrays of
  the same memory layout, calling robosuite's own compiled `opspace_matrices`,
  `nullspace_torques` and `orientation_error`), so the torques are robosuite's to the bit; what
  is constant within a control step for an arm on a fixed base (its origin, the goal in the
  world, the base's zero velocity) is computed once;
- goals are set once per control step by robosuite's own controllers (`set_goal`: the action's
  scaling, input/output ranges, the gripper's `format_action`), and the gripper's command, which
  is constant within a step, is computed once by its controller; the first step after a reset
  is robosuite's own (its lazily updated controller sets that goal from what it read at the
  reset, not from the sim);
- gains, limits and settings are read from robosuite's controller objects, never written here;
- only the observables a caller asks for are sampled, by their own sensors, at the substep where
  robosuite samples them: LIBERO's observables run on a timer that fires one substep before the
  control step ends (at the 24th of 25 after an init state), so its observations lag the sim by
  2 ms; the timer is replayed exactly and written back, so robosuite's own path can take over.

What is skipped changes no trajectory: the robot's history buffers (recent actions, torques,
end-effector velocities), the observables nobody reads, and two of the three BDDL goal checks
per step (the reward's and the step's; the goal check reads the sim and writes nothing).
`supported()` lists the controller settings this path reproduces; any other configuration is
stepped by robosuite itself. tests/test_libero_fast_step.py steps both paths from every task
family's init states and compares the states bit for bit.
"""

from __future__ import annotations

from dataclasses import dataclass

import mujoco
import numpy as np

import suites.robosuite_quiet  # noqa: F401  (before any robosuite import)


class Unsupported(Exception):
    """The env's controller or observables are configured in a way this path does not copy."""


@dataclass
class _Arm:
    """One OSC_POSE arm: its controller, the indices robosuite looks up by name per substep,
    views of MjData with the memory layout robosuite's own copies have (the compiled functions
    have one code path, and make one BLAS call, per layout), and `osc_torques`' buffers."""

    osc: object  # robosuite's OperationalSpaceController
    ref_site: int  # the end-effector site the controller tracks
    base_site: int  # the arm's "<prefix><part>_center" site: the controller's origin
    fixed_base: bool  # the base is welded to the world: its pose is constant, its velocity zero
    qvel_index: np.ndarray  # the arm's dof addresses
    mass_t: np.ndarray  # [7, 7] addresses of the arm's inertia block in qM, transposed (C order)
    actuators: np.ndarray  # the arm's actuators' indices in ctrl
    low: np.ndarray  # their control range
    high: np.ndarray
    ref_pos: np.ndarray  # [3] view of site_xpos
    ref_ori: np.ndarray  # [3, 3] view of site_xmat
    joint_pos: np.ndarray  # [7] of qpos (a view where the arm's joints are contiguous)
    joint_vel: np.ndarray
    bias: np.ndarray  # [7] of qfrc_bias
    J_full: np.ndarray  # robosuite's J_full [6, 7] (C order) and its J_pos, J_ori halves
    J_pos: np.ndarray
    J_ori: np.ndarray
    jacp: np.ndarray  # [3, nv] mj_jacSite's output
    jacr: np.ndarray
    step: np.ndarray  # osc_torques' goal, gains and base velocity for this control step
    mass: np.ndarray  # [7, 7] the inertia block, transposed, as osc_torques last read it
    torques: np.ndarray  # [7] its torques before the clip
    ref_vel: np.ndarray  # [2, 3] the site's linear and angular velocity
    origin: tuple = ()  # the controller's origin (position, orientation) for this control step
    step_ready: bool = False  # `step` holds this control step's values (a fixed base only)


def supported(env) -> None:
    """Raise Unsupported unless `env` (a robosuite env) is set up as LIBERO sets it up."""
    from robosuite.controllers.composite.composite_controller import CompositeController
    from robosuite.controllers.parts.arm.osc import OperationalSpaceController
    from robosuite.controllers.parts.gripper.simple_grip import SimpleGripController

    if not env.lite_physics or len(env.robots) != 1:
        raise Unsupported("needs lite physics and one robot")
    if not env.ignore_done or env.has_renderer:  # the horizon and the viewer are not kept here
        raise Unsupported("an env that ends episodes itself or has a viewer")
    robot = env.robots[0]
    if type(robot.composite_controller) is not CompositeController:
        raise Unsupported(f"composite controller {type(robot.composite_controller).__name__}")
    for part, ctl in robot.composite_controller.part_controllers.items():
        if part in robot.arms:
            if type(ctl) is not OperationalSpaceController:
                raise Unsupported(f"arm controller {type(ctl).__name__}")
            settings = (ctl.impedance_mode, ctl.input_type, ctl.input_ref_frame, ctl.uncoupling,
                        ctl.lite_physics, ctl.num_ref_sites, ctl.interpolator_pos,
                        ctl.interpolator_ori)
            if settings != ("fixed", "delta", "base", True, True, 1, None, None):
                raise Unsupported(f"OSC settings {settings}")
        elif type(ctl) is not SimpleGripController or ctl.interpolator is not None:
            raise Unsupported(f"{part} controller {type(ctl).__name__}")


def _rows(array: np.ndarray, index: np.ndarray) -> np.ndarray:
    """array[index]: a view where the index is a contiguous run (the same values, no copy)."""
    if len(index) and np.array_equal(index, np.arange(index[0], index[0] + len(index))):
        return array[int(index[0]):int(index[0]) + len(index)]
    return array[index]


class FastStepper:
    """Steps one robosuite env (LIBERO's `ControlEnv.env`) as its `step` does, faster.

    Bound to the env's current sim, controllers and observables; `bound_to` says whether they
    are still the env's (a reset may rebuild any of them), and a new stepper is made if not."""

    def __init__(self, env, keys: list[str]):
        from robosuite.utils.observables import NO_CORRUPTION, NO_DELAY, NO_FILTER

        from suites.libero import osc_torques  # imports robosuite's compiled functions

        supported(env)
        self.kernel = osc_torques
        self.env, self.sim = env, env.sim
        self.robot = robot = env.robots[0]
        self.composite = robot.composite_controller
        self.model, self.data = env.sim.model._model, env.sim.data._data
        d = self.data
        # MjData's arrays, once: they view memory that stays put for the data's life
        self.qpos, self.qvel, self.qM, self.ctrl = d.qpos, d.qvel, d.qM, d.ctrl
        self.site_xpos, self.site_xmat = d.site_xpos, d.site_xmat
        self.substeps = int(env.control_timestep / env.model_timestep)  # as robosuite counts
        self.action_dim = robot.action_dim  # robosuite derives it from the limits per substep
        parts = [(part, ctl) for part, ctl in self.composite.part_controllers.items()
                 if robot._enabled_parts.get(part, False)]
        self.arms = [self._arm(part, ctl) for part, ctl in parts if part in robot.arms]
        self.grippers = [(ctl, *self._actuators(part)) for part, ctl in parts
                         if part not in robot.arms]
        # the observables asked for, sampled on robosuite's timer
        self.observables = env._observables
        enabled = [o for o in self.observables.values() if o.is_enabled()]
        missing = [k for k in keys if k not in self.observables
                   or not self.observables[k].is_enabled()]
        if missing:
            raise Unsupported(f"observables {missing} missing or disabled")
        self.wanted = [self.observables[k] for k in keys]
        timers = {(o._time_since_last_sample, o._sampled, o._sampling_timestep, o._current_delay)
                  for o in enabled}
        plain = all(o._corrupter is NO_CORRUPTION and o._filter is NO_FILTER
                    and o._delayer is NO_DELAY for o in enabled)
        if len(timers) != 1 or not plain:
            raise Unsupported("observables with their own timers, noise, filters or delays")
        self.enabled = enabled
        self.period = enabled[0]._sampling_timestep
        self.raw: dict = {}

    def _actuators(self, part: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The part's actuators' indices in ctrl and their control range."""
        index = np.asarray(self.robot._ref_actuators_indexes_dict[part], dtype=np.int64)
        ranges = self.sim.model.actuator_ctrlrange
        return index, np.array(ranges[index, 0]), np.array(ranges[index, 1])

    def _arm(self, part: str, osc) -> _Arm:
        m, d = self.model, self.data
        qvel = np.asarray(osc.qvel_index, dtype=np.int64)
        qpos = np.asarray(osc.qpos_index, dtype=np.int64)
        # where each entry of the arm's inertia block lives in qM: mj_fullM applied to qM's own
        # addresses (1-based, so that 0 marks an entry outside the sparse structure)
        addresses = np.zeros((m.nv, m.nv))
        mujoco.mj_fullM(m, addresses, np.arange(1.0, m.nM + 1.0))
        block = addresses[np.ix_(qvel, qvel)].astype(np.int64) - 1
        if (block < 0).any():
            raise Unsupported("the arm's inertia block is not all in qM")
        ref = self.sim.model.site_name2id(osc.ref_name)
        base = self.sim.model.site_name2id(f"{osc.naming_prefix}{osc.part_name}_center")
        body, fixed = m.site_bodyid[base], True
        while body:  # welded to the world, and no mocap body on the way
            fixed = fixed and m.body_weldid[body] == 0 and m.body_mocapid[body] < 0
            body = m.body_parentid[body]
        actuators, low, high = self._actuators(part)
        n, J_full = len(qvel), np.zeros((6, len(qvel)))
        return _Arm(osc, ref, base, fixed, qvel, np.ascontiguousarray(block.T), actuators, low,
                    high, d.site_xpos[ref], d.site_xmat[ref].reshape(3, 3),
                    _rows(d.qpos, qpos), _rows(d.qvel, qvel), _rows(d.qfrc_bias, qvel),
                    J_full, J_full[:3], J_full[3:], np.zeros((3, m.nv)), np.zeros((3, m.nv)),
                    np.zeros((self.kernel.STEP_ROWS, 3)), np.zeros((n, n)), np.zeros(n),
                    np.zeros((2, 3)))

    def bound_to(self, env) -> bool:
        robot = env.robots[0]
        return (env.sim is self.sim and robot.composite_controller is self.composite
                and env._observables is self.observables
                and all(robot.composite_controller.part_controllers.get(a.osc.part_name) is a.osc
                        for a in self.arms))

    # --- the step ------------------------------------------------------------------------------
    def step(self, action: np.ndarray) -> tuple[dict, bool]:
        """robosuite's `step(action)` for LIBERO: (the observations asked for, BDDL success)."""
        env, m, d = self.env, self.model, self.data
        env.timestep += 1
        self.raw = {o.name: o._current_observed_value for o in self.wanted}  # if none is sampled
        timer = self.enabled[0]
        elapsed, sampled, delay = timer._time_since_last_sample, timer._sampled, timer._current_delay
        last = self.substeps - 1
        for substep in range(self.substeps):
            mujoco.mj_step1(m, d)
            if substep == 0:
                for arm in self.arms:
                    arm.step_ready = False  # a new goal
                self._policy_step(action)
            else:
                for arm in self.arms:
                    self._torques(arm, keep=substep == last)
                if substep == last:
                    self._keep_gripper_state()
            mujoco.mj_step2(m, d)
            # robosuite's Observable.update, for all of them at once (they share one timer)
            elapsed += env.model_timestep
            if not sampled and self.period - delay >= elapsed:
                self._sample()
                sampled = True
            if elapsed >= self.period:
                if not sampled:
                    self._sample()
                elapsed %= self.period
                sampled = False
        for o in self.enabled:
            o._time_since_last_sample, o._sampled = elapsed, sampled
        env.cur_time += env.control_timestep
        env._post_process()  # LIBERO's per-step object-state updates (a light switched on ...)
        return dict(self.raw), bool(env._check_success())

    def _policy_step(self, action: np.ndarray) -> None:
        """robot.control(action, policy_step=True): goals from robosuite's own controllers
        (`set_goal`: the action's scaling and ranges, the gripper's `format_action`), then the
        substep's commands. robosuite updates a controller's state lazily: right after a reset
        it sets the first goal from what the controller read at the reset, not from the sim. That
        step is left to robosuite entirely; otherwise set_goal is handed the state this path reads
        (the two poses its update would read), sparing it the Jacobians and the inertia."""
        if not all(arm.osc.new_update for arm in self.arms) or len(action) != self.action_dim:
            self.env._pre_action(action, policy_step=True)  # robosuite's own (and its errors)
            return
        self.composite.update_state()  # each arm's origin, as robot.control sets it
        for arm in self.arms:
            arm.osc.ref_pos[:] = arm.ref_pos
            arm.osc.ref_ori_mat[:, :] = arm.ref_ori
            arm.osc.new_update = False
        self.composite.set_goal(action)
        for arm in self.arms:
            self._torques(arm)
            arm.osc.new_update = True  # as run_controller leaves it
        for gripper, index, low, high in self.grippers:
            # constant within the step: it stays in data.ctrl for the other substeps
            self.ctrl[index] = np.clip(gripper.run_controller(), low, high)

    def _set_step(self, arm: _Arm) -> None:
        """This control step's origin, goal and gains into `arm.step` (constant within a step on
        a fixed base; an arm on a moving base gets its base's velocity too, every substep)."""
        origin_pos = np.array(self.site_xpos[arm.base_site])
        origin_ori = np.array(self.site_xmat[arm.base_site].reshape([3, 3]))
        base_vel = None
        if not arm.fixed_base:
            mujoco.mj_jacSite(self.model, self.data, arm.jacp, arm.jacr, arm.base_site)
            base_vel = np.dot(arm.jacp, self.qvel), np.dot(arm.jacr, self.qvel)
        self.kernel.step_values(arm.step, arm.osc, origin_pos, origin_ori, base_vel)
        arm.origin, arm.step_ready = (origin_pos, origin_ori), arm.fixed_base

    def _torques(self, arm: _Arm, keep: bool = False) -> None:
        """OperationalSpaceController.update + run_controller + the robot's clip, for the fixed
        impedance, delta input in the base frame, no interpolator (supported()): osc_torques,
        robosuite's operations on the same values, so the same bits. `keep` leaves the state read
        in the controller, as robosuite's last substep does: the first step after a reset sets
        its goal from what the controller last read (robosuite updates it lazily)."""
        osc = arm.osc
        if not arm.step_ready:
            self._set_step(arm)
        mujoco.mj_jacSite(self.model, self.data, arm.jacp, arm.jacr, arm.ref_site)
        self.kernel.osc_torques(*self.osc_arguments(arm))
        if keep:
            osc.update_origin(*arm.origin)
            osc.ref_pos[:], osc.ref_ori_mat[:, :] = arm.ref_pos, arm.ref_ori
            osc.ref_pos_vel[:], osc.ref_ori_vel[:] = arm.ref_vel
            osc.J_pos[:, :], osc.J_ori[:, :], osc.J_full[:, :] = arm.J_pos, arm.J_ori, arm.J_full
            osc.joint_pos, osc.joint_vel = np.array(arm.joint_pos), np.array(arm.joint_vel)
            osc.mass_matrix = arm.mass.T.copy(order="K")  # Fortran order, as robosuite's
            osc.torques, osc.new_update = arm.torques.copy(), True

    def osc_arguments(self, arm: _Arm) -> tuple:
        """`osc_torques`' arguments for the arm: its Jacobians as last computed, MjData's views,
        its buffers. Every output is written before it is read, so a call may be repeated."""
        return (arm.jacp, arm.jacr, self.qvel, arm.qvel_index, self.qM, arm.mass_t, arm.J_full,
                arm.J_pos, arm.J_ori, arm.step, arm.ref_pos, arm.ref_ori, arm.bias,
                arm.osc.initial_joint, arm.joint_pos, arm.joint_vel, arm.low, arm.high, self.ctrl,
                arm.actuators, arm.mass, arm.torques, arm.ref_vel)

    def _keep_gripper_state(self) -> None:
        """What the grippers' controllers read at each substep (GripperController.update); their
        command is constant within a control step and stays in data.ctrl from the policy step."""
        for ctl, *_ in self.grippers:
            ctl.joint_pos = np.array(self.qpos[ctl.qpos_index])
            ctl.joint_vel = np.array(self.qvel[ctl.qvel_index])
            ctl.new_update = True

    def _sample(self) -> None:
        """Observable.update's sampling, for the observables asked for only."""
        cache = self.env._obs_cache
        for o in self.wanted:
            value = np.array(o._sensor(cache))
            value = value[0] if value.ndim == 1 and value.shape[0] == 1 else value
            o._current_observed_value = value
            cache[o.name] = np.array(value)
            self.raw[o.name] = value
