"""The frames' clock: ``t_ns``, integer nanoseconds of a signed 64-bit clock, as a stream takes them and the points
and motion files write them. A module of its own so that the file readers take its bound without importing the
stream (its import pulls OpenCV and the core)."""

MAX_T_NS = 2**63 - 1  # |t_ns|
