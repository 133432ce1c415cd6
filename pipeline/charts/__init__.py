"""Error-against-time charts: what accuracy costs in time, for a person to read.

One chart answers one question ("which solver for live work at 320 x 240?"): the measured
settings as points, error against time on log axes, the Pareto front drawn, every point
labelled without overlap, the shipped default ringed and one sentence read from the data.

- :mod:`pipeline.charts.rows`: benchmark rows (a saved run, the fields a chart reads);
- :mod:`pipeline.charts.decisions`: one view per decision a user makes, rows to charts and tables;
- :mod:`pipeline.charts.sentences`: the sentence under each chart, computed from its points;
- :mod:`pipeline.charts.model`: :class:`~pipeline.charts.model.Point`,
  :class:`~pipeline.charts.model.Chart`, the Pareto front, axis ranges and number formats;
- :mod:`pipeline.charts.labels`: label placement without overlap (shared by both renderers);
- :mod:`pipeline.charts.static`: the charts as matplotlib figures (PNG; the summary figure);
- :mod:`pipeline.charts.page`: an offline interactive page (Plotly, its JavaScript written
  beside the page or embedded in it).

The benchmarks (:mod:`pipeline.charts.decisions`) and the demo report (:mod:`pipeline.workflows.compare_modes`)
build charts from their rows; this package knows nothing of either.
"""
