"""Prefect deployments of hmflow's flows (a scheduled campaign and a report-only rerun) on a
process work pool; see ``deployments/README.md``."""
