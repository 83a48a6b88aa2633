"""Training of the HSCL policy (scripts/train): expert demonstrations, actor, replay, learner, logs.

Layout: expert.py (ODrM* or stand-in expert), demos.py (cached demonstration shards), replay.py
(compact transitions, ring buffer), actor.py (episodes, relabelling, validation; own process),
learner.py (DQN + HSCL updates, checkpoints), log.py (CSV and plot), __main__.py (CLI).
Held-out checks: compare.py (scripts/compare_models), agreement.py (scripts/expert_agreement), failures.py
(scripts/failure_modes).
The second design (issue 20), one process, read top to bottom: dqn_hscl.py (scripts/dqn_hscl), with its ladder of
held-out greedy checks ladder.py (scripts/ladder).
Retired in the fourteenth session, their question answered (models/EXPERIMENTS.md): the offline row collection
and fits (rows.py, fit.py, scripts/collect_rows, scripts/fit_rows); `git show ea9993c:<path>` brings them back.
"""
