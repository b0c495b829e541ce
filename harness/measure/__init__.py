"""Numbers from a run's records: the retention and plasticity metrics (`metrics`), parameter
update statistics and Eq. 8 sparsity (`updates`), and bootstrap confidence intervals. Pure
functions over arrays; imports nothing of the harness.
"""
