"""Small pieces every layer uses: the error types (one-line user errors), atomic file writes, seed
derivation and the compute device. Imports nothing of the harness; suites only for their error.
"""
