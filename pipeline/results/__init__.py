"""Results measured, exported and reported: what the reconstruction's outputs are worth and where they go.

- :mod:`~pipeline.results.evaluate`: angular error of normal maps against truth
  (:func:`angular_error_deg`, :func:`mean_angular_error_deg`, :func:`truth_errors`,
  :func:`evaluate_normals`; ``iristac eval normals``);
- :mod:`~pipeline.results.exports`: files for other tools, a normal-map PNG, a colour-mapped
  depth PNG and a PLY point cloud (:func:`write_pictures`, :func:`write_ply`), and links to the
  store's files (:func:`link_results`);
- :mod:`~pipeline.results.report`: self-contained HTML reports (:class:`Report`).
"""

from pipeline.base.lazy import lazy_names

_WHERE = {"angular_error_deg": "evaluate", "mean_angular_error_deg": "evaluate", "truth_errors": "evaluate",
          "evaluate_normals": "evaluate", "write_pictures": "exports", "write_ply": "exports",
          "link_results": "exports", "Report": "report"}
__getattr__, __dir__ = lazy_names(__name__, _WHERE, globals())

__all__ = list(_WHERE)
