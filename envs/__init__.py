"""envs room: simulation, sensors, closed-loop runner, Gymnasium environments and CLI.

Importing it registers the Gymnasium ids ``viotb/Hover-v0``, ``viotb/Waypoints-v0`` and ``viotb/Track-v0``
(classes in :mod:`viotb.envs.gym`, loaded only by ``gymnasium.make``). ``max_episode_steps`` is the one
place episode length is set (``TimeLimit`` truncates); steps are ``ctrl_dt = 0.02 s`` by default.
"""

from gymnasium import register

register(id="viotb/Hover-v0", entry_point="viotb.envs.gym.hover:HoverEnv", max_episode_steps=500)
register(id="viotb/Waypoints-v0", entry_point="viotb.envs.gym.waypoints:WaypointsEnv", max_episode_steps=1500)
register(id="viotb/Track-v0", entry_point="viotb.envs.gym.track:TrackEnv", max_episode_steps=1000)
