"""Retain's harness: the pipeline that runs a benchmark, one subpackage per step, in data-flow
order. Each may import the ones above it in this list, never one below; suites, policies and
methods sit between them (pyproject.toml's import-linter layers give the exact order):

- `common`: errors, atomic files, seeds, the device; `config`: a benchmark's settings
- `data`: demonstrations (HDF5, LeRobot) and the training data contract methods read
- `train`: the training loop and its optimizer
- `evaluate`: rollouts in simulation, a stage's evaluation, checkpoints
- `measure`: the metrics, update statistics and confidence intervals
- `protocol`: the foundation (stage 0), then each stream stage of one run
- `track`: MLflow, a run's files and figures; `report`: tables and plots over runs
- `run`: the commands, plans, jobs, executors (local, Ray) and studies
- `perf`: speed benchmarks and the GPU check

`benchmarks/` and `studies/` hold the YAML files that `BENCH=` and `STUDY=` name.
pyproject.toml's import-linter contracts (`make lint`) check the order.
"""
