"""sim: the optical ray tracer, the tactile image renderer, lighting modes and the virtual sensor.

Coordinate conventions live in :mod:`pipeline.base.frames`.
"""
