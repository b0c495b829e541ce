"""One training stage: the loop that drives a method's hooks (`trainer`) and the parameter update
(`optim`). Imports methods, data and common; knows nothing of evaluation or tracking.
"""
