"""Shared helpers of every role: errors, colours, file writes, locks, progress."""
