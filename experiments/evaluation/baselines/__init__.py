"""Classical denoising baselines run in time-limited subprocesses, and the sweep aggregator.

* :mod:`experiments.evaluation.baselines.methods` -- the registered methods (CGAL, Open3D, MeshLab).
* :mod:`experiments.evaluation.baselines.runner` -- :func:`run_method`: one method, one cloud, one
  subprocess; failures become records.
* :mod:`experiments.evaluation.baselines.aggregate` -- a directory of ``metrics.json`` files -> one table
  (markdown + JSON) and an accuracy-vs-time chart with the Pareto front.
"""
