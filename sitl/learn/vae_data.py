"""RL+VAE's protocol, before training starts: collect depth images with a flying controller, train a VAE, freeze it."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import torch

from sitl.sim.config import SimConfig
from sitl.sim.env import SwarmEnv
from sitl.sim.episodes import ActorFactory, depth_state_actor


def collect_depth_images(make_actor: ActorFactory, sim_config: SimConfig, seed: int, count: int) -> np.ndarray:
    """``count`` stacked depth images [count, frames, H, W] (float32, metres) seen by the acting UAVs
    while ``make_actor``'s controller flies ``sim_config``'s worlds (finished worlds restart)."""
    env = SwarmEnv(sim_config, seed=seed)
    obs = env.reset()
    act = make_actor(env)
    images = []
    collected = 0
    while collected < count:
        rows = np.flatnonzero(env.acting)
        images.append(obs.depth[rows].astype(np.float16))  # half precision: 20,000 stacks stay small
        collected += len(rows)
        obs, *_ = env.step(act(obs))
        if env.world_done.any():
            obs = env.reset_worlds(env.world_done)
    return np.concatenate(images)[:count].astype(np.float32)


def make_vae_encoder(sim_config: SimConfig, seed: int, images: int, epochs: int, policy_path: str = "",
                     log: Callable[[str], object] = print) -> torch.nn.Module:
    """A trained, frozen VAE encoder for method ``vae``.

    The images are collected with the policy file ``policy_path`` flying, or with the
    straight-to-goal reference when none is given (environment seed ``seed + 7``).
    """
    from sitl.learn.vae import train_vae

    if policy_path:
        from companion.policy import load_policy

        make_actor = depth_state_actor(load_policy(policy_path).act)
        log(f"collecting {images} depth images with {policy_path}")
    else:
        from sitl.sim.baselines import straight_to_goal  # the reference controller (a leaf module)

        make_actor = depth_state_actor(lambda depth, state: straight_to_goal(state))
        log(f"no --vae-policy given: collecting {images} depth images with the straight-to-goal reference")
    data = collect_depth_images(make_actor, sim_config, seed + 7, images)
    encoder, _ = train_vae(data, sim_config.camera.max_range_m, epochs=epochs, seed=seed,
                           progress=lambda e, loss: log(f"VAE epoch {e}/{epochs}: loss {loss:.2f}"))
    return encoder
