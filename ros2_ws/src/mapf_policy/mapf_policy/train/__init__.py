"""Training of the HSCL policy (scripts/train): expert demonstrations, actor, replay, learner, logs.

Layout: expert.py (ODrM* or stand-in expert), demos.py (cached demonstration shards), replay.py
(compact transitions, ring buffer), actor.py (episodes, relabelling, validation; own process),
learner.py (DQN + HSCL updates, checkpoints), log.py (CSV and plot), __main__.py (CLI).
"""
