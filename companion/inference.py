"""Policy inference on its own thread, so the control loop can give up on a late answer."""

from __future__ import annotations

import threading
import time

import numpy as np

from companion.policy import LoadedPolicy


class InferenceWorker:
    """Runs the policy on its own thread, so the control loop can give up on a late answer.

    One job at a time: :meth:`submit` hands over an observation, :meth:`wait` returns the
    answer if it comes before a deadline. A job given up on keeps running (a TorchScript call
    cannot be interrupted); its answer is discarded when it arrives and counted in
    :attr:`discarded`, and until then :attr:`busy_since_s` says the worker is still busy.
    Torch releases the GIL inside its operators, so the loop keeps running meanwhile.
    """

    def __init__(self, policy: LoadedPolicy) -> None:
        self.policy = policy
        self._cv = threading.Condition()
        self._job: tuple[int, np.ndarray, np.ndarray] | None = None
        self._results: dict[int, tuple[np.ndarray | None, BaseException | None, float]] = {}
        self._abandoned: set[int] = set()
        self._next_id = 0
        self._stop = False
        self.busy_since_s: float | None = None  # monotonic start of the job in progress
        self.discarded: list[float] = []  # durations (s) of late answers thrown away, for the log
        self._thread = threading.Thread(target=self._run, name="policy-inference", daemon=True)

    #: Calls on a blank observation in the worker thread before the first real one: TorchScript's
    #: profiling executor optimises per thread on the first calls (~20 ms instead of ~1.3 ms on the
    #: bundled policy here), which would otherwise make the first engaged step late.
    WARMUP_CALLS = 3

    def start(self) -> None:
        """Start the thread and return once it has warmed the policy up."""
        import torch  # noqa: PLC0415 - the policy's runtime is already loaded

        self._threads = torch.get_num_threads()  # the CLI's choice (1), applied in the worker too
        self._warm = threading.Event()
        self._thread.start()
        self._warm.wait(timeout=60.0)

    def _warm_up(self) -> None:
        depth, state = self.policy.blank_observation()  # a goal ahead in an empty world
        for _ in range(self.WARMUP_CALLS):
            try:
                self.policy.act(depth, state)
            except Exception:  # noqa: BLE001 - a failing policy is reported by the first real call
                break
        self._warm.set()

    def submit(self, depth: np.ndarray, state: np.ndarray) -> int:
        """Start inference on a copy of the observation; return the job id."""
        with self._cv:
            self._next_id += 1
            self._job = (self._next_id, np.array(depth, dtype=np.float32), np.array(state, dtype=np.float32))
            self.busy_since_s = time.monotonic()
            self._cv.notify_all()
            return self._next_id

    def wait(self, job_id: int, deadline_s: float) -> tuple[np.ndarray | None, BaseException | None, float] | None:
        """(output, error, seconds) of ``job_id``, or None if not done by ``deadline_s`` (it is then abandoned)."""
        with self._cv:
            while job_id not in self._results:
                remaining = deadline_s - time.monotonic()
                if remaining <= 0:
                    self._abandoned.add(job_id)
                    return None
                self._cv.wait(remaining)
            return self._results.pop(job_id)

    def _run(self) -> None:
        import torch  # noqa: PLC0415

        torch.set_num_threads(self._threads)
        self._warm_up()
        while True:
            with self._cv:
                while self._job is None and not self._stop:
                    self._cv.wait()
                if self._stop:
                    return
                job_id, depth, state = self._job
                self._job = None
            started = time.perf_counter()
            output = error = None
            try:
                output = np.asarray(self.policy.act(depth, state), dtype=np.float64).reshape(-1)
            except Exception as err:  # noqa: BLE001 - a TorchScript runtime error is reported, not fatal
                error = err
            seconds = time.perf_counter() - started
            with self._cv:
                self.busy_since_s = None
                if job_id in self._abandoned:
                    self._abandoned.discard(job_id)
                    self.discarded.append(seconds)
                else:
                    self._results[job_id] = (output, error, seconds)
                self._cv.notify_all()

    def close(self) -> None:
        with self._cv:
            self._stop = True
            self._cv.notify_all()
        if self._thread.is_alive():
            self._thread.join(timeout=0.2)  # a call in progress cannot be interrupted: it is a daemon
