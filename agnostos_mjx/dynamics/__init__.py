"""X-ICM's dynamics diffusion model in Flax NNX, and dynamics-guided demo selection.

Modules: config (presets), data (FramePairs), autoencoder, text, unet, diffusion
(schedule, loss, DDIM), checkpoint (orbax), pipeline (trained models, batched
inference), export_format (the compact float16 shipping format: files, checks,
reading), export (writing one from a training run), features (vis.in / vis.out /
lang, selection, cached index).
Training entry points live in agnostos_mjx.train.
"""
