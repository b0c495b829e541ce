"""Success in simulation: rollouts of a policy on fixed evaluation episodes (`rollouts`), and a
stage's evaluation record with its held-out loss, plus checkpoints (`stages`). Imports methods
(a task-aware method is evaluated in its own view), data, policies, config, common and suites;
nothing of training.
"""
