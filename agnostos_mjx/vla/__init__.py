"""The reference in-domain VLA (issue 28): virtual views (views.py), the network
(model.py) and its checkpoints (checkpoint.py); trained by ``agnostos_mjx.train.vla``,
evaluated as the policy ``reference-vla`` (policies/reference_vla.py)."""
