"""Events -> predictions: the chains of data of each wagon, the block state carried and
re-anchored through them, and the predicted sensor and contact temperatures stored per event."""
