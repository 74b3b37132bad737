"""Synthetic fleets: registry, log files with the imperfections of real units, injected
anomalies and an undeclared effect, and the truth they were made from."""
