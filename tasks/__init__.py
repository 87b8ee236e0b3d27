"""Thin Prefect tasks over hmcore and storage: each one loads, calls the domain, stores."""
