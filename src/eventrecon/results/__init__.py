"""What a run leaves: its records (metrics, curves, versions) and machine facts."""
