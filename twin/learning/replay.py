"""Replay memory ``B_d`` of every drone (Sec. III-A), in preallocated numpy arrays.

One ring buffer of swarm steps, shape ``(capacity, n_drones, ...)``: row ``t`` holds the
transition ``(s_d, u_d, r_d, s'_d, U_d(s'))`` of every drone ``d`` at that step, so the union
``U_d B_d`` (central coordination) is sampled over ``(step, drone)`` pairs, and the buffer of
one drone (decentralized mode) is the view ``[:, d]`` (:meth:`ReplayBuffer.drone`). The
feasible-action mask of the next state is stored because the Bellman target's argmax runs
over feasible actions only. A buffer of n-step transitions (:func:`n_step_transitions`) also
stores each row's bootstrap discount ``gamma^m``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from twin.grid import N_ACTIONS


@dataclass
class Batch:
    """A sample of transitions, numpy arrays with a leading batch axis."""

    states: np.ndarray  # (B, S) float32, S the state variant's size
    actions: np.ndarray  # (B,) int64
    rewards: np.ndarray  # (B,) float32
    next_states: np.ndarray  # (B, S) float32
    next_feasible: np.ndarray  # (B, 5) bool
    #: (B,) float32 discount of the bootstrap term, ``gamma^m`` (None: the scalar ``gamma``)
    discounts: np.ndarray | None = None


def n_step_transitions(
    rewards: np.ndarray,
    next_states: np.ndarray,
    next_feasible: np.ndarray,
    gamma: float,
    n: int,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The n-step transitions of one episode, from its 1-step arrays (leading axes ``(T, N)``).

    For step ``t`` and drone ``d``, with ``m = min(n, T - t)`` (truncated at the episode's
    end): the return ``sum_{i<m} gamma^i r_{t+i,d}`` of the drone's own rewards, the state
    ``s_{t+m,d}`` reached ``m`` steps later with its feasible actions, and the bootstrap
    discount ``gamma^m`` of the Double DQN target ``Y = R + gamma^m Q(s_{t+m}, ...)``. The
    episode's end is a time limit, not a terminal state, so the last steps still bootstrap.
    Vectorised: one array operation per offset ``i < n``, none per transition.
    Returns ``(returns, next_states, next_feasible, discounts)``, discounts of shape ``(T,)``.
    """
    if n < 1:
        raise ValueError(f"n_step must be at least 1, got {n}")
    horizon = len(rewards)
    returns = np.zeros(rewards.shape, dtype=np.float64)
    for i in range(min(n, horizon)):
        returns[: horizon - i] += gamma**i * rewards[i:].astype(np.float64)
    steps = np.minimum(n, horizon - np.arange(horizon))
    last = np.arange(horizon) + steps - 1  # index of the 1-step transition that ends at t + m
    discounts = (gamma ** steps.astype(np.float64)).astype(np.float32)
    return returns.astype(np.float32), next_states[last], next_feasible[last], discounts


class ReplayBuffer:
    """Ring buffer of ``capacity`` swarm steps of ``n_drones`` transitions each, of states of
    ``state_size`` values (the state variant's, :mod:`twin.states`)."""

    def __init__(
        self, capacity: int, n_drones: int, *, state_size: int, discounted: bool = False
    ) -> None:
        if capacity < 1 or n_drones < 1 or state_size < 1:
            raise ValueError(
                f"capacity, n_drones and state_size must be positive, got {capacity}, "
                f"{n_drones}, {state_size}"
            )
        self.capacity, self.n_drones = int(capacity), int(n_drones)
        shape = (self.capacity, self.n_drones)
        self.states = np.zeros((*shape, state_size), dtype=np.float32)
        self.actions = np.zeros(shape, dtype=np.int64)
        self.rewards = np.zeros(shape, dtype=np.float32)
        self.next_states = np.zeros((*shape, state_size), dtype=np.float32)
        self.next_feasible = np.zeros((*shape, N_ACTIONS), dtype=bool)
        # per-row bootstrap discount gamma^m of n-step transitions (None: the scalar gamma)
        self.discounts = np.zeros(self.capacity, dtype=np.float32) if discounted else None
        self.cursor = 0  # next row to write
        self.steps = 0  # rows filled, <= capacity

    def __len__(self) -> int:
        """Number of stored transitions over all drones."""
        return self.steps * self.n_drones

    def add(
        self,
        states: np.ndarray,
        actions: np.ndarray,
        rewards: np.ndarray,
        next_states: np.ndarray,
        next_feasible: np.ndarray,
    ) -> None:
        """Store one swarm step: every argument has a leading ``n_drones`` axis."""
        if self.discounts is not None:
            raise ValueError("a discounted buffer takes whole episodes (add_steps)")
        t = self.cursor
        self.states[t] = states
        self.actions[t] = actions
        self.rewards[t] = rewards
        self.next_states[t] = next_states
        self.next_feasible[t] = next_feasible
        self.cursor = (t + 1) % self.capacity
        self.steps = min(self.steps + 1, self.capacity)

    def add_steps(
        self,
        states: np.ndarray,
        actions: np.ndarray,
        rewards: np.ndarray,
        next_states: np.ndarray,
        next_feasible: np.ndarray,
        discounts: np.ndarray | None = None,
    ) -> None:
        """Store many swarm steps at once (leading axes ``(steps, n_drones)``); ``discounts``
        ``(steps,)``: their bootstrap discounts, required by a ``discounted`` buffer."""
        n = len(actions)
        if (discounts is None) != (self.discounts is None):
            raise ValueError("give discounts exactly when the buffer was made discounted")
        rows = (self.cursor + np.arange(n)) % self.capacity
        if discounts is not None:
            self.discounts[rows] = discounts
        self.states[rows] = states
        self.actions[rows] = actions
        self.rewards[rows] = rewards
        self.next_states[rows] = next_states
        self.next_feasible[rows] = next_feasible
        self.cursor = int((self.cursor + n) % self.capacity)
        self.steps = min(self.steps + n, self.capacity)

    def sample(self, batch_size: int, rng: np.random.Generator, drone: int | None = None) -> Batch:
        """Uniform sample from the pooled buffers, or from drone ``drone``'s own buffer."""
        if self.steps == 0:
            raise ValueError("cannot sample from an empty replay buffer")
        rows = rng.integers(0, self.steps, size=batch_size)
        cols = (
            rng.integers(0, self.n_drones, size=batch_size)
            if drone is None
            else np.full(batch_size, drone)
        )
        return Batch(
            self.states[rows, cols],
            self.actions[rows, cols],
            self.rewards[rows, cols],
            self.next_states[rows, cols],
            self.next_feasible[rows, cols],
            None if self.discounts is None else self.discounts[rows],
        )

    def drone(self, d: int) -> DroneView:
        """The buffer ``B_d`` of one drone, as views (no copy)."""
        return DroneView(self, d)


class DroneView:
    """Read-only view of one drone's column of a :class:`ReplayBuffer`."""

    def __init__(self, buffer: ReplayBuffer, d: int) -> None:
        if not 0 <= d < buffer.n_drones:
            raise IndexError(f"drone {d} not in 0..{buffer.n_drones - 1}")
        self.buffer, self.d = buffer, d

    def __len__(self) -> int:
        return self.buffer.steps

    @property
    def states(self) -> np.ndarray:
        return self.buffer.states[: self.buffer.steps, self.d]

    @property
    def actions(self) -> np.ndarray:
        return self.buffer.actions[: self.buffer.steps, self.d]

    @property
    def rewards(self) -> np.ndarray:
        return self.buffer.rewards[: self.buffer.steps, self.d]

    @property
    def next_states(self) -> np.ndarray:
        return self.buffer.next_states[: self.buffer.steps, self.d]

    @property
    def next_feasible(self) -> np.ndarray:
        return self.buffer.next_feasible[: self.buffer.steps, self.d]

    def sample(self, batch_size: int, rng: np.random.Generator) -> Batch:
        return self.buffer.sample(batch_size, rng, drone=self.d)
