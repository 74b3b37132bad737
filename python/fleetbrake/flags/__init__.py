"""Predictions -> flags: detectors of sensor faults, weak, dragging and overheating brakes, their
configuration, and the flags stored in the warehouse."""
