"""Flags and predictions -> a new model revision: the residual's evidence, candidate effects,
their fit and choice, and the close-loop report."""
