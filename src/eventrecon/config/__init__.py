"""Hydra configuration: resolvers, dataset names, override checks."""
