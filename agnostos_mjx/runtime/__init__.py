"""The batched environment: one EnvState pytree, the key action written once over one
physics boundary, observations.  Imports point down: env -> key_action / phase / observe
-> state -> outcome.  Import from the modules (runtime.env.Episodes, runtime.outcome.Outcome):
this package file imports nothing, so importing a small module stays cheap."""
