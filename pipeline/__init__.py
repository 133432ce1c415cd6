"""pipeline: the stage store, capture, normals, depth, orchestration, benchmarks and the CLI."""

__version__ = "0.1.0"
