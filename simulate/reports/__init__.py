"""Fidelity and stability reports of the cloth simulator (issue 7).

- :mod:`simulate.reports.scenes`: report scenes (a garment or shawl on the default body, or a
  cloth towel on a capsule for CI) and a batched driver that takes each world from the canonical
  drape through a pose path to rest, with per-world metrics.
- :mod:`simulate.reports.accuracy`: error against run time over solver settings (``drape report accuracy``).
- :mod:`simulate.reports.stability`: the stiff / extreme case matrix (``drape report stability``).
- :mod:`simulate.reports.pareto`: Pareto front and the error-vs-time plot (also used by ``drape evaluate``).
"""
