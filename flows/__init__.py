"""Prefect flows: each reads like its DAG."""
