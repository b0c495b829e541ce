"""Where results go: MLflow runs (`tracking`, `server` for a loopback `mlflow server`), a run's
files and figures under results/ (`run_outputs`, `figures`). Imports config and common only.
"""
