"""The tracking reward and termination that both tasks share (the follower env's one agent, the swarm's followers).

`task_terms` is the readable law, `task_kernel` its compiled twin, which the engine
(`downwash_envs.engine.TaskWorlds`) runs every step; a test compares them. Written for A
agents per world: the follower task has one, the swarm task one per follower.

Shapes: W worlds, V vehicles, A agents; positions m, velocities m/s, actions m/s^2, all
world frame, z up.
"""

from __future__ import annotations

import numpy as np

from downwash_core.jit import njit
from downwash_core.status import Status
from downwash_envs.config import FollowerConfig

__all__ = ["REWARD_TERMS", "INFO_KEYS", "ERROR_CAP", "task_constants", "task_terms", "task_kernel", "squared_norm"]

# Reward terms, summed in this order: reward = sum(info["reward_" + name] for name in REWARD_TERMS).
REWARD_TERMS = ("alive", "position", "velocity", "action", "action_rate", "termination")
# A step's info, in this order: the reward terms, the errors (m, m/s; true state, capped), the status code.
INFO_KEYS = (*(f"reward_{k}" for k in REWARD_TERMS), "position_error", "velocity_error", "status")
_OK, _LEFT_BOX = int(Status.OK), int(Status.LEFT_BOX)  # plain ints: no enum conversion per step

ERROR_CAP = 10.0  # m and m/s: position/velocity errors in the reward are capped (a diverged state is not finite)


def task_constants(task: FollowerConfig, bound: float) -> np.ndarray:
    """(8,) float64: max_tracking_error (m), the six reward weights in REWARD_TERMS order (the
    costs negated, so that each term is weight * value), and bound^2 (m^2/s^4)."""
    return np.array([
        task.max_tracking_error, task.alive_reward, -task.position_cost_weight, -task.velocity_cost_weight,
        -task.action_cost_weight, -task.action_rate_cost_weight, -task.termination_penalty, bound * bound,
    ])  # fmt: skip


def task_terms(
    true_pos: np.ndarray, true_vel: np.ndarray, ref_pos: np.ndarray, ref_vel: np.ndarray, agents: np.ndarray,
    actions: np.ndarray, last_action: np.ndarray, sim_status: np.ndarray, constants: np.ndarray,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The readable reward and termination of a step (the envs run its compiled twin `task_kernel`).

    true_pos, true_vel, ref_pos, ref_vel: (W, V, 3) m, m/s at the end of the step; agents (A,);
    actions, last_action: (W, A, 3) m/s^2 (this step's, the previous); sim_status: (W,) the
    simulator's `Status` codes; constants: `task_constants`. Returns status (W,) int64 (the
    simulator's, else LEFT_BOX when any agent is farther than max_tracking_error from its
    reference, else OK), terms (6, W, A) in REWARD_TERMS order, reward (W, A) (their sum in
    that order), position and velocity errors (W, A), capped
    at ERROR_CAP (non-finite: the cap). The world's end is every agent's.
    """
    max_err, alive, w_p, w_v, w_a, w_da, w_end, b2 = constants
    pos_err = _capped(np.sqrt(squared_norm(true_pos[:, agents] - ref_pos[:, agents])))
    vel_err = _capped(np.sqrt(squared_norm(true_vel[:, agents] - ref_vel[:, agents])))
    left = ~np.all(pos_err <= max_err, axis=1)
    status = np.where(sim_status != _OK, sim_status, np.where(left, _LEFT_BOX, _OK)).astype(np.int64)
    ended = np.repeat((status != _OK)[:, None], len(agents), axis=1).astype(np.float64)  # (W, A) 1.0 / 0.0
    terms = np.stack([
        alive * (1.0 - ended), w_p * pos_err, w_v * vel_err, w_a * (squared_norm(actions) / b2),
        w_da * (squared_norm(actions - last_action) / b2), w_end * ended,
    ])  # fmt: skip
    reward = np.zeros(pos_err.shape)
    for term in terms:
        reward = reward + term
    return status, terms, reward, pos_err, vel_err


def _capped(n: np.ndarray) -> np.ndarray:
    return np.where(n <= ERROR_CAP, n, ERROR_CAP)


@njit
def _capped_distance(x, y):
    """|x - y| of two (3,) vectors, summed x, y, z left to right; non-finite or above ERROR_CAP: the cap."""
    dx, dy, dz = x[0] - y[0], x[1] - y[1], x[2] - y[2]
    e = np.sqrt(dx * dx + dy * dy + dz * dz)
    return e if e <= ERROR_CAP else ERROR_CAP


@njit
def task_kernel(true_pos, true_vel, ref_pos, ref_vel, agents, actions, last_action, sim_status, constants,
                 status, terms, reward, pos_err, vel_err):
    """Compiled `task_terms`, written into status (W,), terms (6, W, A), reward, pos_err, vel_err (W, A)."""
    W, A = pos_err.shape
    max_err, alive, w_p, w_v = constants[0], constants[1], constants[2], constants[3]
    w_a, w_da, w_end, b2 = constants[4], constants[5], constants[6], constants[7]
    for w in range(W):
        inside = True
        for i in range(A):
            a = agents[i]
            pos_err[w, i] = _capped_distance(true_pos[w, a], ref_pos[w, a])
            vel_err[w, i] = _capped_distance(true_vel[w, a], ref_vel[w, a])
            inside = inside and pos_err[w, i] <= max_err
        if sim_status[w] != _OK:
            status[w] = sim_status[w]
        elif not inside:
            status[w] = _LEFT_BOX
        else:
            status[w] = _OK
        ended = 1.0 if status[w] != _OK else 0.0
        for i in range(A):
            ax, ay, az = actions[w, i, 0], actions[w, i, 1], actions[w, i, 2]
            dx, dy, dz = ax - last_action[w, i, 0], ay - last_action[w, i, 1], az - last_action[w, i, 2]
            terms[0, w, i] = alive * (1.0 - ended)
            terms[1, w, i] = w_p * pos_err[w, i]
            terms[2, w, i] = w_v * vel_err[w, i]
            terms[3, w, i] = w_a * ((ax * ax + ay * ay + az * az) / b2)
            terms[4, w, i] = w_da * ((dx * dx + dy * dy + dz * dz) / b2)
            terms[5, w, i] = w_end * ended
            r = 0.0
            for k in range(6):
                r = r + terms[k, w, i]
            reward[w, i] = r


def squared_norm(x: np.ndarray) -> np.ndarray:
    """(..., 3) -> (...) squared norm, summed x, y, z left to right (as the compiled kernels)."""
    return x[..., 0] * x[..., 0] + x[..., 1] * x[..., 1] + x[..., 2] * x[..., 2]
