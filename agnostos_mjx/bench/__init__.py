"""Benchmarks and reports: commands that measure the library, kept out of its packages.

Each module runs as ``python -m agnostos_mjx.bench.<name>``: ``backends`` (physics steps/s
and oracle episodes/s per backend), ``observation`` (camera-frames/s), ``dynamics`` (the
dynamics model's training steps/s and query features), ``query_flops`` (the selection's
arithmetic per query), ``selection`` (which seen tasks X-ICM draws demos from),
``object_text`` (X-ICM's object text from segmented point clouds), ``llm`` (LLM request
concurrency), ``remote_policy`` (a served policy's cost).  Nothing here is imported by the
library.
"""
