"""Training of the HSCL policy (scripts/train): expert demonstrations, actor, replay, learner, logs.

Layout: expert.py (ODrM* or stand-in expert), demos.py (cached demonstration shards), replay.py
(compact transitions, ring buffer), actor.py (episodes, relabelling, validation; own process),
learner.py (DQN + HSCL updates, checkpoints), log.py (CSV and plot), __main__.py (CLI).
Held-out checks: compare.py (scripts/compare_models), agreement.py (scripts/expert_agreement). Offline:
rows.py (expert-labelled states on disk, scripts/collect_rows), fit.py (supervised fits on them, scripts/fit_rows).
"""
