"""The evaluator behind ``python -m agnostos_mjx.eval``, one job per module.

Imports point one way: run -> rollout, scheduler, records, summary -> protocol, config.

* config: EvalConfig, the command line generated from it, the policy it names;
* protocol: seeds, episode keys, variations, tasks and groups (what an episode is);
* rollout: the episodes of one task, batch by batch, and their records;
* scheduler: tasks overlapped while a policy waits (on an LLM, a policy server);
* records: episodes.jsonl (load, repair, append) and resuming a run;
* summary: aggregation, results.json/.csv/.md/.png, merging processes' runs;
* processes: one run as several processes on this machine (--local-processes);
* run: `evaluate(cfg)` and its output folder;
* video, report_plot, paper: episode videos, the results' plot, the published numbers;
* experts_check: the experts on every variation (``python -m
  agnostos_mjx.evaluation.experts_check``).
"""
