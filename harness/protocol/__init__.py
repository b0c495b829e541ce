"""The benchmark protocol for one (method, seed): the cached foundation and its stage-0
evaluation (`foundation`), then each stream stage trained, checked and evaluated (`stream`).
Imports measure, evaluate, train and everything below them; not tracking or the commands.
"""
