"""Physical constants shared by the pipeline and the simulator (one home each)."""

G_MPS2 = 9.80665
"""Standard gravity [m/s^2] (CGPM 1901): converts accelerometer readings in g and is the specific force of a sensor
at rest."""
