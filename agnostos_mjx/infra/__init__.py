"""Plumbing shared by every layer: settings, the GPU's memory and CUDA MPS, sharding over
devices, CUDA graphs, gathered requests, the command-line helpers and statistics."""
