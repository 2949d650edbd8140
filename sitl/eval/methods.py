"""What flies the swarm in an evaluation: a policy file or a reference controller, as a :class:`Method`.

``resolve_method("straight" | "orca" | "orca-fov" | ... | PATH)`` (:data:`BASELINES` or a policy file) loads and checks it; ``Method.make_actor(env)``
builds its :data:`sitl.sim.episodes.Actor` for one environment.
"""

from __future__ import annotations

import dataclasses
import hashlib
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from companion.face_goal import FaceGoalSpec
from companion.governor import DEFAULT_GOVERNOR, GovernorSpec, governor_name
from companion.spec import DEFAULT_ACTION_SPEC, CameraSpec, MemorySpec
from sitl.eval.orca import ORCA_REFERENCES
from sitl.sim.env import Observation, SwarmEnv
from sitl.sim.episodes import Actor, ActorFactory, face_goal_actor, governed_actor

DEFAULT_POLICY = Path("models/policy.pt")


#: The ORCA references (sitl.eval.orca): all UAVs known, or only those in the camera's view (keeping right
#: when one of them closes in; or never forgetting one it saw, after a look around at the start or without).
ORCA_BASELINES = tuple(ORCA_REFERENCES)
BASELINES = ("straight", *ORCA_BASELINES)
#: Appended to a controller's label when the speed governor follows it (``+governor-NAME`` for a preset other
#: than the default, ``companion.governor.GOVERNOR_PRESETS``).
GOVERNED_SUFFIX = "+governor"
#: Appended to a controller's label when it turns to face its goal before flying (``companion.face_goal``).
FACE_GOAL_SUFFIX = "+face-goal"


class EvaluationError(ValueError):
    """A request the evaluation cannot serve (missing policy, impossible scenario...), with the reason."""


@dataclass
class Method:
    """Something that flies the swarm: a policy file or a reference controller."""

    label: str  # short name in tables: "straight", "orca" or the policy's method ("sac_ae")
    kind: str  # "policy" or "baseline"
    path: str | None = None  # policy file
    camera: CameraSpec | None = None  # the policy's camera: the simulated camera must match it
    control_period_s: float | None = None
    provenance: dict = field(default_factory=dict)
    governor: GovernorSpec | None = None  # companion.governor on the commands (label gains "+governor")
    memory: MemorySpec | None = None  # the policy's remembered-depth input: the simulator builds it
    face_goal: FaceGoalSpec | None = None  # companion.face_goal before the flight (label gains "+face-goal")
    _policy: object = field(default=None, repr=False)

    def info(self) -> dict:
        """What the JSON says about the controller."""
        out = {"label": self.label, "kind": self.kind}
        if self.governor is not None:
            out["governor"] = self.governor.to_dict()
        if self.face_goal is not None:
            out["face_goal"] = dataclasses.asdict(self.face_goal)
        if self.path:
            out |= {"path": self.path, "sha256": file_digest(self.path),
                    "camera": self.camera.to_dict() if self.camera else None, "provenance": self.provenance}
        if self.kind == "baseline" and self.label in ORCA_BASELINES:
            from sitl.eval.orca import baseline_orca

            params, _, sees_obstacles = baseline_orca(self.label)
            out["orca"] = params.to_dict() | {"sees_obstacles": sees_obstacles}
        return out

    def make_actor(self, env: SwarmEnv) -> Actor:
        """This controller's :data:`~sitl.sim.episodes.Actor` for every UAV of ``env`` (an :data:`ActorFactory`)."""
        actor = self._make_ungoverned_actor(env)
        if self.face_goal is not None:  # before the governor, as in the companion
            action = getattr(self._policy, "action", None) or DEFAULT_ACTION_SPEC
            actor = face_goal_actor(actor, self.face_goal, env, float(action.high_array()[2]))
        if self.governor is None:
            return actor
        return governed_actor(actor, self.governor, env)

    @property
    def trained_with_governor(self) -> bool:
        """A policy file that carries its governor (policy.json ``governor``): it always flies with it."""
        return getattr(self._policy, "governor", None) is not None

    def with_governor(self, spec: GovernorSpec) -> Method:
        """The same controller with the speed governor after it (:mod:`companion.governor`). One that already
        has one (a policy trained with it) keeps its own, as the companion does."""
        if self.governor is not None:
            return self
        name = governor_name(spec)
        suffix = GOVERNED_SUFFIX if name in (DEFAULT_GOVERNOR, "custom") else f"{GOVERNED_SUFFIX}-{name}"
        return dataclasses.replace(self, label=self.label + suffix, governor=spec)

    def with_face_goal(self, spec: FaceGoalSpec) -> Method:
        """The same controller, turning in place to face its goal for ``spec.hold_s`` before it flies
        (:mod:`companion.face_goal`)."""
        if self.governor is not None:  # the suffixes' order is the order they act in
            base = self.label.split(GOVERNED_SUFFIX)[0]
            label = base + FACE_GOAL_SUFFIX + self.label[len(base):]
        else:
            label = self.label + FACE_GOAL_SUFFIX
        return dataclasses.replace(self, label=label, face_goal=spec)

    def _make_ungoverned_actor(self, env: SwarmEnv) -> Actor:
        # the controller the face-goal start and the governor follow
        name = self.label.split(FACE_GOAL_SUFFIX)[0].split(GOVERNED_SUFFIX)[0]
        if self.kind == "baseline" and name == "straight":
            from sitl.sim.baselines import straight_actor

            return straight_actor(env)
        if self.kind == "baseline" and name in ORCA_BASELINES:
            from sitl.eval.orca import baseline_orca, orca_actor

            # Privileged ORCA knows the obstacles too; the camera-limited ones only the UAVs they see.
            params, camera_limited, see_obstacles = baseline_orca(name)
            return orca_actor(env, params, camera_limited=camera_limited, see_obstacles=see_obstacles)
        return policy_actor(self._policy)(env)


def policy_actor(policy) -> ActorFactory:
    """The factory of a loaded policy file's actor (:class:`companion.policy.LoadedPolicy`).

    The policy runs in one batch over the acting UAVs of every world (the finished ones cost
    nothing), as its TorchScript module frozen and optimised for inference.
    """
    module = _fast_module(policy)

    def bind(env: SwarmEnv) -> Actor:
        def act(obs: Observation) -> np.ndarray:
            import torch

            out = np.zeros((env.num_agents, 3), dtype=np.float32)
            rows = np.flatnonzero(env.acting)
            if rows.size:
                depth = torch.from_numpy(np.ascontiguousarray(obs.depth[rows], dtype=np.float32))
                state = torch.from_numpy(np.ascontiguousarray(obs.state[rows], dtype=np.float32))
                with torch.inference_mode():
                    out[rows] = module(depth, state).numpy()
            return out

        return act

    return bind


def _fast_module(policy):
    """The policy's TorchScript module frozen and optimised for inference (~25 % faster on CPU).

    Falls back to the module as loaded if the optimisation fails; the output is the same
    to float32 rounding either way.
    """
    import torch

    from companion.policy import _QuietJitDeprecation

    try:
        with _QuietJitDeprecation():
            return torch.jit.optimize_for_inference(torch.jit.freeze(policy.module.eval()))
    except Exception:  # noqa: BLE001 - an optimisation, never a reason to fail
        return policy.module


def file_digest(path: str | Path) -> str:
    """First 16 hex digits of a file's SHA-256 (identifies the policy a result belongs to)."""
    digest = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()[:16]


def missing_policy_message(path: str | Path) -> str:
    return (f"policy file {path} not found. Train one (python -m sitl.train, which writes RUN_DIR/policy.pt, "
            f"then copy it to {DEFAULT_POLICY}) or choose another controller: --policy straight (no avoidance), "
            "--policy orca (privileged ORCA), --policy orca-fov (ORCA knowing only the UAVs in its camera's view), "
            "--policy orca-fov-right (orca-fov keeping right of the UAVs it sees closing in), "
            "--policy orca-fov-right80 (the same turning 80 instead of 40 deg), "
            "--policy orca-fov-memory (orca-fov never forgetting a UAV it saw), --policy orca-fov-look-around "
            "(orca-fov-memory after a look all around at the start) or --policy PATH (a policy file)")


def resolve_method(spec: str | Path) -> Method:
    """A reference controller (:data:`BASELINES`) or a policy file (loaded and validated) as a :class:`Method`."""
    if str(spec) in BASELINES:
        if str(spec) in ORCA_BASELINES:
            from sitl.eval.orca import _import_rvo

            try:
                _import_rvo()
            except ImportError as err:
                raise EvaluationError(str(err)) from None
        return Method(label=str(spec), kind="baseline")
    from companion.policy import PolicyFileError, load_policy

    path = Path(spec)
    if not path.exists():
        raise EvaluationError(missing_policy_message(path))
    try:
        policy = load_policy(path)
    except PolicyFileError as err:
        raise EvaluationError(f"cannot use {path} as a policy: {err}") from None
    provenance = policy.metadata.get("provenance", {}) or {}
    label = str(provenance.get("method") or path.stem)
    method = Method(label=label, kind="policy", path=str(path), camera=policy.camera,
                    control_period_s=policy.control_period_s, provenance=provenance, memory=policy.memory,
                    _policy=policy)
    # A policy trained with the speed governor flies with it, as the companion flies it.
    return method.with_governor(policy.governor) if policy.governor is not None else method
