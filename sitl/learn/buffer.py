"""Replay buffer that stores every depth frame once.

A transition's observation is a stack of the last ``k`` frames and its next observation is
the same stack shifted by one new frame, so storing ``obs`` and ``next_obs`` as images would
keep each frame ``2k`` times. Here frames live once in a ring (float16 metres: ~1 cm
resolution at 20 m) and a transition keeps the indices of its ``k + 1`` frames.

Memory: ``frame_capacity * H * W * 2`` bytes of frames, with ``frame_capacity = 2 *
capacity + 8 * agents`` (every transition adds one frame, every episode start adds one,
and an episode has at least one transition, so a frame is never overwritten while a
transition that uses it is alive), plus ~76 bytes of vectors per transition. For the
default 20,000 transitions of 32x32 images and 128 agents that is 85 MB — a plain
obs/next_obs buffer of float32 stacks would take 492 MB.
"""

from __future__ import annotations

import numpy as np
import torch


class FrameReplayBuffer:
    """Transitions of many agents sharing one policy (centralised training, paper Alg. 1)."""

    def __init__(self, capacity: int, num_agents: int, frames: int, height: int, width: int, state_dim: int,
                 action_dim: int, seed: int = 0, privileged_dim: int = 0, frame_ages: tuple[int, ...] | None = None,
                 precollision_steps: int = 0) -> None:
        """``privileged_dim`` > 0: every transition also keeps the critic's privileged input for its
        observation and its next one (asymmetric critic, :mod:`sitl.learn.privileged`).
        ``frame_ages``: age in steps of each stacked frame, oldest first, ending in 0
        (``CameraSpec.stack_ages``; default: consecutive frames).
        ``precollision_steps`` > 0: a UAV's last that many transitions before a collision are marked,
        and :meth:`sample` can draw part of a batch from them (``precollision_fraction``)."""
        self.capacity = capacity
        self.frames_per_obs = frames
        ages = tuple(frame_ages) if frame_ages is not None else tuple(range(frames - 1, -1, -1))
        if len(ages) != frames:
            raise ValueError(f"frame_ages {list(ages)} must give one age per stacked frame ({frames})")
        history = ages[0] + 1  # frames an agent's observation reaches back over
        self.frame_columns = np.array([history - 1 - a for a in ages], dtype=np.int64)  # the stacked ones among them
        self.frame_capacity = 2 * capacity + (8 + history) * num_agents
        self.frame_store = np.zeros((self.frame_capacity, height, width), dtype=np.float16)
        # The agent's frame history before the step, then the new frame: the observation is the
        # frame_columns of the first `history` columns, the next one the same from column 1 on.
        self.frame_index = np.zeros((capacity, history + 1), dtype=np.int64)
        self.state = np.zeros((capacity, state_dim), dtype=np.float32)
        self.next_state = np.zeros((capacity, state_dim), dtype=np.float32)
        self.action = np.zeros((capacity, action_dim), dtype=np.float32)
        self.reward = np.zeros((capacity, 1), dtype=np.float32)
        self.not_done = np.zeros((capacity, 1), dtype=np.float32)
        # A privileged teacher's action in [-1, 1] where one was given (teacher-guided training), else invalid.
        self.teacher_action = np.zeros((capacity, action_dim), dtype=np.float32)
        self.teacher_valid = np.zeros((capacity, 1), dtype=np.float32)
        self.privileged = np.zeros((capacity, privileged_dim), dtype=np.float32)
        self.next_privileged = np.zeros((capacity, privileged_dim), dtype=np.float32)
        # Links to the same agent's next transition, for n-step returns. A link holds the
        # stamp (insertion count) of its target so that an overwritten row is not followed.
        self.stamp = np.full(capacity, -1, dtype=np.int64)
        self.successor = np.full(capacity, -1, dtype=np.int64)
        self.successor_stamp = np.full(capacity, -2, dtype=np.int64)
        self.size = 0
        self._next = 0
        self._next_frame = 0
        self._frames_stored = 0  # frames ever stored: until it reaches frame_capacity, the ring's tail is unused
        self._inserted = 0
        self.agent_stack = np.zeros((num_agents, history), dtype=np.int64)  # each agent's current frame history
        self.agent_last_row = np.full(num_agents, -1, dtype=np.int64)  # its previous transition this episode
        # Each agent's last precollision_steps rows this episode (oldest first, -1: none) with their
        # stamps, so that a collision marks only rows that still hold that agent's transitions.
        self.precollision = np.zeros(capacity, dtype=bool)
        self.agent_recent = np.full((num_agents, precollision_steps), -1, dtype=np.int64)
        self.agent_recent_stamp = np.full((num_agents, precollision_steps), -2, dtype=np.int64)
        self.rng = np.random.default_rng(seed)

    @property
    def nbytes(self) -> int:
        arrays = (self.frame_store, self.frame_index, self.state, self.next_state, self.action, self.reward, self.not_done,
                  self.teacher_action, self.teacher_valid, self.privileged, self.next_privileged)
        return sum(a.nbytes for a in arrays)

    def _store_frames(self, frames: np.ndarray) -> np.ndarray:
        count = frames.shape[0]
        idx = (self._next_frame + np.arange(count)) % self.frame_capacity
        self.frame_store[idx] = frames
        self._next_frame = (self._next_frame + count) % self.frame_capacity
        self._frames_stored += count
        return idx

    def start_episodes(self, agents: np.ndarray, first_frames: np.ndarray) -> None:
        """Agents ``agents`` start an episode whose first image is ``first_frames`` [k, H, W]."""
        if len(agents) == 0:
            return
        idx = self._store_frames(first_frames)
        self.agent_stack[agents] = idx[:, None]
        self.agent_last_row[agents] = -1
        self.agent_recent[agents] = -1

    def add(self, agents: np.ndarray, state: np.ndarray, action: np.ndarray, reward: np.ndarray,
            next_frames: np.ndarray, next_state: np.ndarray, terminated: np.ndarray,
            teacher_action: np.ndarray | None = None, teacher_valid: np.ndarray | None = None,
            privileged: np.ndarray | None = None, next_privileged: np.ndarray | None = None,
            collided: np.ndarray | None = None) -> None:
        """Store one step of the agents in ``agents`` (all arrays have one row per agent listed).

        ``terminated`` means the episode truly ended (arrival or collision): no bootstrap.
        A time-out is not terminal (its next state is still worth something).
        ``teacher_action``: a teacher's action in [-1, 1] for the same observation, where
        ``teacher_valid`` (default: everywhere it is given; nowhere without it).
        ``privileged``/``next_privileged``: the critic's extra input before and after the step
        (required when the buffer was built with ``privileged_dim`` > 0). ``collided``: the agents
        whose step ended in a collision (marks their approach when ``precollision_steps`` > 0).
        """
        count = len(agents)
        if count == 0:
            return
        new_frames = self._store_frames(next_frames)
        rows = (self._next + np.arange(count)) % self.capacity
        self.frame_index[rows, :-1] = self.agent_stack[agents]
        self.frame_index[rows, -1] = new_frames
        self.state[rows] = state
        self.action[rows] = action
        self.reward[rows, 0] = reward
        self.next_state[rows] = next_state
        self.not_done[rows, 0] = 1.0 - terminated.astype(np.float32)
        if teacher_action is None:
            self.teacher_valid[rows, 0] = 0.0
        else:
            self.teacher_action[rows] = teacher_action
            self.teacher_valid[rows, 0] = 1.0 if teacher_valid is None else teacher_valid.astype(np.float32)
        if self.privileged.shape[1]:
            if privileged is None or next_privileged is None:
                raise ValueError("this buffer keeps privileged inputs: add() needs privileged and next_privileged")
            self.privileged[rows] = privileged
            self.next_privileged[rows] = next_privileged
        self.agent_stack[agents] = np.concatenate([self.agent_stack[agents, 1:], new_frames[:, None]], axis=1)
        stamps = self._inserted + np.arange(count)
        self.stamp[rows] = stamps
        self.successor[rows] = -1
        previous = self.agent_last_row[agents]
        linked = previous >= 0
        self.successor[previous[linked]] = rows[linked]
        self.successor_stamp[previous[linked]] = stamps[linked]
        self.agent_last_row[agents] = np.where(terminated, -1, rows)
        self.precollision[rows] = False  # overwritten rows lose an old mark
        if self.agent_recent.shape[1]:
            self.agent_recent[agents] = np.concatenate([self.agent_recent[agents, 1:], rows[:, None]], axis=1)
            self.agent_recent_stamp[agents] = np.concatenate([self.agent_recent_stamp[agents, 1:], stamps[:, None]],
                                                             axis=1)
            if collided is not None and collided.any():
                recent, recent_stamp = self.agent_recent[agents[collided]], self.agent_recent_stamp[agents[collided]]
                valid = (recent >= 0) & (self.stamp[np.maximum(recent, 0)] == recent_stamp)
                self.precollision[recent[valid]] = True
        self._inserted += count
        self._next = (self._next + count) % self.capacity
        self.size = min(self.size + count, self.capacity)

    def sample(self, batch_size: int, device: torch.device, n_step: int = 1, gamma: float = 0.99,
               with_teacher: bool = False, precollision_fraction: float = 0.0) -> dict[str, torch.Tensor]:
        """A uniform batch; depth comes back as float32 metres [B, k, H, W].

        ``precollision_fraction``: that share of the batch is drawn uniformly from the transitions
        marked as a collision's approach (while there are any), the rest uniformly from all.

        ``with_teacher``: the batch also carries ``teacher_action`` and ``teacher_valid``. A buffer
        with privileged inputs adds ``privileged`` (of the observation) and ``next_privileged`` (of
        the observation the n-step target bootstraps from).

        With ``n_step > 1`` each transition is extended along its agent's episode by up to
        ``n_step - 1`` further transitions: ``reward`` is the discounted sum and
        ``discount`` is ``gamma^m`` (0 after a terminal step) for the ``m`` steps taken.
        """
        rows = self.rng.integers(0, self.size, size=batch_size)
        if precollision_fraction > 0:
            marked = np.flatnonzero(self.precollision[: self.size])
            hot = min(int(round(precollision_fraction * batch_size)), batch_size) if len(marked) else 0
            if hot:
                rows[:hot] = marked[self.rng.integers(0, len(marked), size=hot)]
        last = rows.copy()
        reward = self.reward[rows, 0].astype(np.float64)
        factor = np.ones(batch_size)
        extending = np.ones(batch_size, dtype=bool)
        for _ in range(n_step - 1):
            nxt = self.successor[last]
            extending &= (nxt >= 0) & (self.not_done[last, 0] > 0)
            extending &= self.stamp[np.maximum(nxt, 0)] == self.successor_stamp[last]
            if not extending.any():
                break
            factor = np.where(extending, factor * gamma, factor)
            last = np.where(extending, nxt, last)
            reward += np.where(extending, factor * self.reward[last, 0], 0.0)
        discount = factor * gamma * self.not_done[last, 0]
        columns = self.frame_columns
        obs_frames = self.frame_store[self.frame_index[rows[:, None], columns]]
        next_frames = self.frame_store[self.frame_index[last[:, None], columns + 1]]
        to = lambda a: torch.from_numpy(np.ascontiguousarray(a, dtype=np.float32)).to(device)  # noqa: E731
        batch = {
            "depth": to(obs_frames),
            "next_depth": to(next_frames),
            "state": to(self.state[rows]),
            "action": to(self.action[rows]),
            "reward": to(reward[:, None]),
            "next_state": to(self.next_state[last]),
            "not_done": to(self.not_done[last]),
            "discount": to(discount[:, None]),
        }
        if self.privileged.shape[1]:
            batch |= {"privileged": to(self.privileged[rows]), "next_privileged": to(self.next_privileged[last])}
        if with_teacher:
            batch |= {"teacher_action": to(self.teacher_action[rows]), "teacher_valid": to(self.teacher_valid[rows])}
        return batch

    #: Arrays with one row per transition; rows 0 .. size - 1 are the filled ones (rows fill in order).
    _ROW_ARRAYS = ("frame_index", "state", "next_state", "action", "reward", "not_done", "stamp", "successor",
                   "successor_stamp", "teacher_action", "teacher_valid", "privileged", "next_privileged",
                   "precollision")

    def state_dict(self) -> dict:
        """Everything needed to resume, with only the *filled* part of the preallocated arrays.

        A checkpoint early in a run (or of a large capacity) would otherwise write the whole
        preallocated buffer: 905 MB for a capacity of 200,000 holding 176 transitions.
        """
        frames_used = min(self._frames_stored, self.frame_capacity)
        arrays = {name: np.ascontiguousarray(getattr(self, name)[: self.size]) for name in self._ROW_ARRAYS}
        arrays["frame_store"] = np.ascontiguousarray(self.frame_store[:frames_used])
        scalars = {k: v for k, v in vars(self).items() if k not in arrays and k not in ("rng", "frame_store")}
        return scalars | arrays | {"rng": self.rng.bit_generator.state}

    def load_state_dict(self, state: dict) -> None:
        """Restore :meth:`state_dict` output (or an older checkpoint holding the whole arrays) into this buffer."""
        if state["capacity"] != self.capacity or state["frame_capacity"] != self.frame_capacity:
            raise ValueError(f"checkpoint buffer has capacity {state['capacity']} ({state['frame_capacity']} frames), "
                             f"this one {self.capacity} ({self.frame_capacity} frames)")
        state = dict(state)
        if "_frames_stored" not in state:  # older checkpoints saved the whole ring: treat it as used
            state["_frames_stored"] = self.frame_capacity
        for key, value in state.items():
            if key == "rng":
                self.rng.bit_generator.state = value
            elif key in self._ROW_ARRAYS or key == "frame_store":
                target = getattr(self, key)
                if value.shape[1:] != target.shape[1:] or len(value) > len(target):
                    raise ValueError(f"checkpoint buffer array {key} has shape {value.shape}, expected at most "
                                     f"{target.shape}")
                target[: len(value)] = value
            else:
                setattr(self, key, value)
