"""The reproduction of the paper's Ansys study: manoeuvres A and B, calibration, the figures and
VTU fields."""
