"""Dynamics backends behind one interface (:class:`sitl.sim.dynamics.base.Dynamics`).

``kinematic`` (default) is a fast first-order velocity-tracking model; ``jsbsim`` flies
one JSBSim rigid-body quadrotor per UAV under a velocity controller.
"""

from __future__ import annotations

from sitl.sim.dynamics.base import Dynamics
from sitl.sim.dynamics.kinematic import (RESPONSE_PRESETS, KinematicDynamics, KinematicParams, KinematicRandomization,
                                        describe_response, layer_response, nominal_ranges, parse_response)

DYNAMICS_NAMES = ("kinematic", "jsbsim")


def make_dynamics(name: str, num_uavs: int) -> Dynamics:
    """Build the backend called ``name`` for ``num_uavs`` UAVs."""
    if name == "kinematic":
        return KinematicDynamics(num_uavs)
    if name == "jsbsim":
        from sitl.sim.dynamics.jsbsim_quad import JSBSimDynamics  # jsbsim loads slowly; only when asked

        return JSBSimDynamics(num_uavs)
    raise ValueError(f"unknown dynamics {name!r}; choose one of {', '.join(DYNAMICS_NAMES)}")


__all__ = ["DYNAMICS_NAMES", "RESPONSE_PRESETS", "Dynamics", "KinematicDynamics", "KinematicParams", "KinematicRandomization",
           "describe_response", "layer_response", "make_dynamics", "nominal_ranges", "parse_response"]
