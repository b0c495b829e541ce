"""Demonstrations in, training data out: expert demos cached as HDF5 in LIBERO's layout
(`demos`), LeRobot datasets in and out (`lerobot`), and the tensors a stage trains on
(`prepare`). `datasets` is the data contract that methods import. Imports config, common,
suites, and the policies' instruction encoder.
"""
