"""Training and evaluation entry points of the dynamics diffusion model (issue 6) and of
the reference VLA (issue 28: ``vla_data``, ``vla``).

python -m agnostos_mjx.train.autoencoder --help
python -m agnostos_mjx.train.dynamics --help
python -m agnostos_mjx.train.evaluate --help
"""
