"""Stage 4, a run: scenario + terrain + solver -> snapshots and summaries.

- :mod:`avflow.simulation.runner`: output times, stop rule, the :class:`RunResult`;
- :mod:`avflow.simulation.summary`: runout, deposit extent, travel angle.

(Named ``simulation`` rather than ``run`` so that :func:`avflow.run` stays the function.)
"""
