"""Retain's scheduler: config, data, training loop, evaluation, metrics, tracking, reports, CLI."""
