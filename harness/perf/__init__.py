"""Figures, not tests: training, evaluation and method throughput (`throughput`, `make
bench-train`, `bench-eval`, `bench-methods`), MLflow under load (`tracking_load`), the LeRobot
reader's speed (`lerobot`) and the GPU check (`gpu_check`). The top layer: imports anything.
"""
