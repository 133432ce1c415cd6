"""pipeline: the base layer (``pipeline.base``), capture, normals, depth, the stage registry
(``pipeline.stages``), the entry points, benchmarks and the CLI.

Kept light on purpose: importing ``pipeline.base`` runs this file, and the base layer must
not pull anything above it.
"""

__version__ = "0.1.0"
