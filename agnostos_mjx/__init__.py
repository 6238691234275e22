"""agnostos-mjx: the AGNOSTOS cross-task benchmark and X-ICM in MuJoCo / MJX.

Importing the package has no side effects; the commands set up JAX themselves
(`agnostos_mjx.infra.settings.configure_jax`)."""

__version__ = "0.1.0"
