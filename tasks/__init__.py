"""VirSqueezer method steps: one module per step (pure functions + their cached Prefect task)."""
