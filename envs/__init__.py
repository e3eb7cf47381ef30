"""envs room."""
