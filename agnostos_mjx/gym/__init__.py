"""The gymnasium VectorEnv (env.py) and its options (options.py).  Import from the
modules, or from ``agnostos_mjx.gym_env``: this package file imports nothing."""
