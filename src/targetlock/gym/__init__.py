"""Gymnasium environments of targetlock; importing this module registers them.

    import gymnasium, targetlock.gym
    env = gymnasium.make("targetlock/TargetLock-v0")                 # randomised scopes, ideal tracker
    env = gymnasium.make("targetlock/TargetLock-v0", observation="image")   # rendered frames
    envs = gymnasium.make_vec("targetlock/TargetLock-v0", num_envs=256)     # batch kernel

See :class:`targetlock.gym.env.TargetLockEnv` for spaces, reward and randomisation, and
:class:`targetlock.gym.vector.TargetLockVectorEnv` for the vector environment.
"""
from gymnasium.envs.registration import register, registry

from .env import TargetLockEnv, random_case
from .vector import TargetLockVectorEnv

__all__ = ["TargetLockEnv", "TargetLockVectorEnv", "random_case", "ENV_ID"]

ENV_ID = "targetlock/TargetLock-v0"

if ENV_ID not in registry:
    register(id=ENV_ID, entry_point="targetlock.gym.env:TargetLockEnv", disable_env_checker=False,
             vector_entry_point="targetlock.gym.vector:TargetLockVectorEnv")
